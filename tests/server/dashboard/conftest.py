"""Browser tests: the dashboard in a real headless Chromium (Debian's ``chromium``, driven by Playwright),
against a real ``crowdslam demo``. Under CI=true a missing browser fails the run instead of skipping."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from playwright.sync_api import Browser, Page, Route, sync_playwright

from server.cli.background_server import CLI, free_port
from tests.conftest import write_testbed

LOOPBACK = {"127.0.0.1", "localhost", "::1", "[::1]"}


def chromium_path() -> str | None:
    for name in (os.environ.get("CROWDSLAM_CHROMIUM", ""), "chromium", "chromium-browser"):
        if name and (found := shutil.which(name)):
            return found
    return None


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    """Module-scoped: Playwright's sync API keeps an event loop running in the main thread while it is open,
    and later tests that call ``asyncio.run`` would find it."""
    path = chromium_path()
    if path is None:
        message = "no chromium on PATH (apt-get install chromium, or set CROWDSLAM_CHROMIUM)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"the dashboard's browser tests need Chromium under CI=true: {message}")
        pytest.skip(message)
    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=path, args=["--no-sandbox"])
        yield launched
        launched.close()


@dataclass
class Watch:
    """What a page did that it must not: requests off loopback (aborted), console errors, page errors."""

    off_loopback: list[str] = field(default_factory=list)
    console_errors: list[str] = field(default_factory=list)

    def assert_clean(self) -> None:
        assert self.off_loopback == [], f"requests off loopback: {self.off_loopback}"
        assert self.console_errors == [], f"console errors: {self.console_errors}"


def open_page(browser: Browser, watch: Watch, viewport: tuple[int, int] = (1280, 800)) -> Page:
    context = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]})

    def guard(route: Route) -> None:
        url = route.request.url
        host = urlsplit(url).hostname or ""
        if urlsplit(url).scheme in ("http", "https", "ws", "wss") and host not in LOOPBACK:
            watch.off_loopback.append(url)
            route.abort()
        else:
            route.continue_()

    context.route("**/*", guard)
    page = context.new_page()

    def off_loopback(url: str) -> None:
        if (urlsplit(url).hostname or "") not in LOOPBACK and url not in watch.off_loopback:
            watch.off_loopback.append(url)

    page.on("request", lambda request: off_loopback(request.url))
    page.on("websocket", lambda socket: off_loopback(socket.url))
    page.on("console", lambda m: watch.console_errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: watch.console_errors.append(f"page error: {e}"))
    return page


def wait_for(predicate: object, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():  # type: ignore[operator]
            return
        time.sleep(0.2)
    raise AssertionError(f"not within {timeout_s:.0f} s: {what}")


@dataclass
class Demo:
    base: str
    dashboard_link: str
    dashboard_key: str
    operator_key: str
    building: str
    process: subprocess.Popen[str]
    data_dir: Path


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Demo]:
    """``crowdslam demo`` at real-time pace: its crowd walks for minutes, so positions keep changing."""
    folder = tmp_path_factory.mktemp("demo")
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(folder / "data")}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    env.pop("CROWDSLAM_BUILDING_PROCESSES", None)  # the default: processes on more than one core
    port = free_port()
    scenario = write_testbed(folder / "small.json", users=10)
    args = [*CLI, "demo", "--port", str(port), "--speed", "1", "--scenario", str(scenario)]
    process = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    deadline = time.monotonic() + 240
    assert process.stdout is not None
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            break
        lines.append(line)
        if "Ctrl-C stops" in line:
            break
    out = "".join(lines)
    link = re.search(r"dashboard:\s+(\S+)", out)
    operator = re.search(r"operator key:\s+(\S+)", out)
    if link is None or operator is None:
        process.kill()
        pytest.fail(f"crowdslam demo did not start:\n{out[-3000:]}")
    key = re.search(r"#key=([^&\s]+)", link.group(1))
    assert key is not None
    try:
        yield Demo(
            f"http://127.0.0.1:{port}",
            link.group(1),
            key.group(1),
            operator.group(1),
            "demo",
            process,
            folder / "data",
        )
    finally:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        process.stdout.close()
