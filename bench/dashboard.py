"""Dashboard benchmark: the dashboard page in headless Chromium (Debian's ``chromium``, driven by Playwright)
watching a building of N simulated users, each updating once a second.

    python bench/dashboard.py [--users 2000] [--duration 60] [--json OUT]

A real server (the app under uvicorn on loopback, SQLite in a temporary folder) serves the page and the live
socket. The users' estimates are published straight into the server's live fan-out, a tenth of them every
100 ms, each stamped with the wall-clock time it was published: the page, not the tracker, is what this
measures (``bench/load.py`` measures the tracker). Users walk at 1.4 m/s in a 120 x 90 m floor with a
covariance that breathes, so every ellipse and trail changes every second.

Reports ``fps`` (requestAnimationFrame callbacks per second over the run, and the lowest of any 1 s window
after the first 10 s), the page's JS heap after a garbage collection at 10 s and at the end, and its growth,
and ``ws_lag`` (p50/p99): the newest estimate the page has drawn, behind the wall clock, sampled every 250 ms.
Targets: fps >= 30 and heap growth <= 20 % after the first 10 s.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from server.slam.numba_cache import configure_numba_cache

configure_numba_cache()

import httpx
from fastapi import FastAPI
from playwright.sync_api import sync_playwright
from report import emit
from tqdm import tqdm

from schemas.api import KeyScope
from schemas.common import Position
from schemas.estimates import Estimate, EstimateSource
from schemas.live import PositionMessage
from server.app import create_app
from server.auth import mint_key
from server.cli.background_server import free_port, running_server
from server.live.broadcast import live_json
from server.settings import Settings
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade

WIDTH_M, HEIGHT_M = 120.0, 90.0
SLICES = 10  # publishes a second; each carries a tenth of the users


def _crowd_publisher(app: FastAPI, building: str, users: int, duration_s: float) -> None:
    """A route that starts, inside the server's event loop, the task publishing the crowd's estimates."""
    rng = random.Random(0)
    xy = [[rng.uniform(0, WIDTH_M), rng.uniform(0, HEIGHT_M)] for _ in range(users)]
    heading = [rng.uniform(-math.pi, math.pi) for _ in range(users)]

    async def publish() -> None:
        broadcaster = app.state.crowdslam.broadcaster
        start = time.monotonic()
        tick = 0
        while time.monotonic() - start < duration_s:
            now_ms = int(time.time() * 1000)
            texts = []
            for u in range(tick % SLICES, users, SLICES):
                heading[u] += rng.gauss(0, 0.3)
                x = xy[u][0] + 1.4 * math.cos(heading[u])
                y = xy[u][1] + 1.4 * math.sin(heading[u])
                if not (0 <= x <= WIDTH_M and 0 <= y <= HEIGHT_M):
                    heading[u] += math.pi
                    x, y = xy[u]
                xy[u] = [x, y]
                var = 0.5 + 2.0 * (1 + math.sin(now_ms / 4000 + u)) / 2
                estimate = Estimate(
                    building_id=building, user_id=f"u{u}", device_id=f"d{u}", t_ms=now_ms,
                    position=Position(x_m=x, y_m=y), covariance_m2=[[var, 0.3 * var], [0.3 * var, 0.6 * var]],
                    heading_rad=heading[u] % (2 * math.pi) - math.pi, source=EstimateSource.DYNAMICSLAM,
                )  # fmt: skip
                texts.append(live_json(PositionMessage(estimate=estimate)))
            broadcaster.publish_texts(building, texts)
            tick += 1
            await asyncio.sleep(max(0.0, start + tick / SLICES - time.monotonic()))

    tasks: set[asyncio.Task[None]] = set()

    @app.post("/bench/crowd", include_in_schema=False)
    async def start_crowd() -> dict[str, int]:
        task = asyncio.get_running_loop().create_task(publish())
        tasks.add(task)
        return {"users": users}


MEASURE = """
() => {
  const m = window.__bench = { frames: [], lags: [], draw: [], messages: [] };
  const root = document.getElementById('app');
  const d = window.crowdslamDashboard;
  const timed = (object, name, into) => {
    const original = object[name].bind(object);
    object[name] = (...args) => {
      const t0 = performance.now();
      const r = original(...args);
      into.push(performance.now() - t0);
      return r;
    };
  };
  timed(d.view, 'draw', m.draw);
  timed(d, 'onLive', m.messages);
  const tick = (t) => { m.frames.push(t); requestAnimationFrame(tick); };
  requestAnimationFrame(tick);
  setInterval(() => {
    const drawn = Number(root.dataset.updatedMs);
    if (drawn > 0) m.lags.push(Date.now() - drawn);
  }, 250);
}
"""


def _heap_mb(cdp: Any) -> float:
    cdp.send("HeapProfiler.collectGarbage")
    return float(cdp.send("Runtime.getHeapUsage")["usedSize"]) / 2**20


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q / 100 * len(ordered)))] if ordered else float("nan")


def run(users: int, duration_s: float, chromium: str) -> dict[str, Any]:
    folder = Path(tempfile.mkdtemp(prefix="crowdslam-dashboard-bench-"))
    try:
        settings = Settings(data_dir=folder, record=False)
        engine = make_engine(settings.resolved_database_url)
        upgrade(engine)
        with make_session_factory(engine).begin() as session:
            operator, _ = mint_key(session, KeyScope.OPERATOR)
        engine.dispose()
        app = create_app(settings)
        _crowd_publisher(app, "mall", users, duration_s + 15)
        with running_server(app, "127.0.0.1", free_port()) as base, httpx.Client(base_url=base) as client:
            auth = {"Authorization": f"Bearer {operator}"}
            floor = {"level": 0, "name": "Ground", "width_m": WIDTH_M, "height_m": HEIGHT_M}
            client.post("/v1/buildings", json={"id": "mall", "name": "Mall", "floors": [floor]}, headers=auth)
            key = client.post("/v1/buildings/mall/keys", json={"scope": "dashboard"}, headers=auth).json()[
                "key"
            ]
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
                page = browser.new_page(viewport={"width": 1400, "height": 860})
                page.goto(f"{base}/dashboard/#key={key}&building=mall")
                page.wait_for_selector("#app[data-connection='connected']", timeout=30_000)
                cdp = page.context.new_cdp_session(page)
                client.post("/bench/crowd")
                page.evaluate(MEASURE)
                heap_start = _heap_mb(cdp)
                started = time.monotonic()
                heap_10s = None
                with tqdm(total=int(duration_s), desc=f"{users} users", unit="s", leave=False) as bar:
                    while (elapsed := time.monotonic() - started) < duration_s:
                        if heap_10s is None and elapsed >= 10:
                            heap_10s = _heap_mb(cdp)
                        time.sleep(0.5)
                        bar.n = int(min(elapsed, duration_s))
                        bar.refresh()
                measured = page.evaluate("() => window.__bench")
                heap_end = _heap_mb(cdp)
                drawn = int(page.locator("#app").get_attribute("data-users") or 0)
                page.screenshot(path=str(folder / "last.png"))
                browser.close()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    frames = measured["frames"]
    span_s = (frames[-1] - frames[0]) / 1000 if len(frames) > 1 else float("nan")
    windows = [
        sum(1 for f in frames if s * 1000 <= f - frames[0] < (s + 1) * 1000) for s in range(10, int(span_s))
    ]
    heap_10 = heap_10s if heap_10s is not None else heap_start
    return {
        "users": users,
        "users_drawn": drawn,
        "duration_s": duration_s,
        "fps": round((len(frames) - 1) / span_s, 1),
        "fps_min_1s_after_10s": min(windows) if windows else None,
        "heap_mb_start": round(heap_start, 1),
        "heap_mb_10s": round(heap_10, 1),
        "heap_mb_end": round(heap_end, 1),
        "heap_growth_after_10s": round(heap_end / heap_10 - 1, 3),
        "draw_ms_p50": round(_percentile(measured["draw"], 50), 2),
        "draw_ms_p99": round(_percentile(measured["draw"], 99), 2),
        "draws_per_s": round(len(measured["draw"]) / span_s, 1),
        "message_frame_ms_p50": round(_percentile(measured["messages"], 50), 2),
        "ws_lag_p50_ms": round(_percentile(measured["lags"], 50)),
        "ws_lag_p99_ms": round(_percentile(measured["lags"], 99)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--users", type=int, default=2000)
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures to this file")
    args = parser.parse_args()
    result = run(args.users, args.duration, args.chromium)
    result["targets_met"] = result["fps"] >= 30 and result["heap_growth_after_10s"] <= 0.20
    emit(result, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
