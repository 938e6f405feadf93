"""Screenshots of the dashboard for the README, taken from a running demo in headless Chromium:

    python docs/screenshots.py [--out docs/img] [--chromium PATH]

Starts ``crowdslam demo`` (the paper testbed, real-time pace) in a temporary folder, waits for the crowd to
walk for a while, then takes the live view with one person selected (``dashboard-live.png``), an operator
pinning an anchor (``dashboard-operator.png``) and the history slider replaying the crowd
(``dashboard-history.png``)."""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from playwright.sync_api import Page, sync_playwright  # noqa: E402

from server.cli.background_server import CLI, free_port  # noqa: E402

WALK_S = 45.0  # the crowd walks this long before the first picture (ellipses shrink as anchors are met)


def start_demo(folder: Path) -> tuple[subprocess.Popen[str], str, str, str]:
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(folder)}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    port = free_port()
    process = subprocess.Popen(
        [*CLI, "demo", "--port", str(port), "--speed", "1"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert process.stdout is not None
    out = ""
    while "Ctrl-C stops" not in out:
        line = process.stdout.readline()
        if not line:
            raise SystemExit(f"crowdslam demo did not start:\n{out}")
        out += line
    link = re.search(r"dashboard:\s+(\S+)", out)
    operator = re.search(r"operator key:\s+(\S+)", out)
    if link is None or operator is None:
        raise SystemExit(f"crowdslam demo printed no dashboard link or operator key:\n{out}")
    return process, f"http://127.0.0.1:{port}", link.group(1), operator.group(1)


def click_first(page: Page, collection: str) -> None:
    """Click the first person (``users``) or anchor (``anchors``) where the page draws it."""
    x, y = page.evaluate(
        f"() => {{ const d = window.crowdslamDashboard; const v = [...d.scene.{collection}.values()]"
        f".sort((a, b) => (a.id < b.id ? -1 : 1))[0]; const p = v.est ? v.est.position : v.position;"
        f" return d.view.toScreen(p.x_m, p.y_m); }}"
    )
    page.locator("#map").click(position={"x": x, "y": y})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "img")
    parser.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix="crowdslam-screenshots-"))
    process, base, link, operator = start_demo(folder)
    try:
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=args.chromium, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1400, "height": 860})
            page.goto(link)
            page.wait_for_selector("#app[data-connection='connected']", timeout=60_000)
            time.sleep(WALK_S)
            click_first(page, "users")
            page.screenshot(path=str(args.out / "dashboard-live.png"))
            print(f"wrote {args.out / 'dashboard-live.png'}")

            page.goto(f"{base}/dashboard/#key={operator}&building=demo")
            page.reload()
            page.wait_for_selector("#app[data-connection='connected']", timeout=60_000)
            page.locator("#pin-type").select_option("elevator")
            page.fill("#pin-label", "north lift")
            page.click("#pin-pick")
            page.locator("#map").click(position={"x": 520, "y": 300})
            page.click("#pin-submit")
            said = "() => document.getElementById('message').textContent !== ''"
            page.wait_for_function(said, timeout=10_000)
            if "Pinned" not in page.locator("#message").inner_text():
                raise SystemExit(f"the pin was refused: {page.locator('#message').inner_text()}")
            page.locator("#keys-card summary").click()
            page.wait_for_selector("#keys tbody tr", timeout=10_000)
            page.screenshot(path=str(args.out / "dashboard-operator.png"))
            print(f"wrote {args.out / 'dashboard-operator.png'}")

            page.locator("#live-toggle").uncheck()
            slider = page.locator("#history")
            slider.evaluate(
                "(s) => { s.value = String(Number(s.max) - 25); s.dispatchEvent(new Event('input')); }"
            )
            time.sleep(1.5)
            page.click("#play")
            time.sleep(2.0)
            page.click("#play")
            time.sleep(0.5)
            page.screenshot(path=str(args.out / "dashboard-history.png"))
            print(f"wrote {args.out / 'dashboard-history.png'}")
            browser.close()
    finally:
        process.send_signal(signal.SIGINT)
        process.wait(timeout=120)
        if process.stdout is not None:
            process.stdout.close()
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
