"""The phone page in headless Chromium against a real ``crowdslam serve``, a building with a real floor's
plan, and a real walk's IMU played into the page through Chrome DevTools Protocol sensor emulation."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from playwright.sync_api import CDPSession, Page

from server.cli.background_server import free_port, migrate_with_operator_key, serve_process
from server.datasets.msindoor import Trace, read_floor, read_floor_plan, read_trace
from tests.conftest import SAMPLE_FLOOR
from tests.server.dashboard.conftest import browser

__all__ = ["browser"]  # the dashboard's module-scoped Chromium, shared

WALK = SAMPLE_FLOOR / "path_data_files" / "5ddb9632c5b77e0006b179b1.txt"
"""The sample's longest walk: 16 s, 25 steps by the server's PDR."""


@dataclass
class PhoneServer:
    base: str
    operator: str
    data_dir: Path

    def auth(self, key: str) -> dict[str, str]:
        return {"Authorization": f"Bearer {key}"}

    def building(self, building_id: str, upper_floors: int = 0) -> None:
        """A building whose ground floor is the sample floor, with its plan (and upper floors of its size
        without one)."""
        floor = read_floor(SAMPLE_FLOOR)
        plan = read_floor_plan(floor).plan
        assert plan is not None
        size = {"width_m": floor.width_m, "height_m": floor.height_m}
        floors = [{"level": level, "name": f"F{level + 1}", **size} for level in range(1 + upper_floors)]
        body = {"id": building_id, "name": f"Mall {building_id}", "floors": floors}
        created = httpx.post(f"{self.base}/v1/buildings", json=body, headers=self.auth(self.operator))
        assert created.status_code == 201, created.text
        put = httpx.put(
            f"{self.base}/v1/buildings/{building_id}/floors/0/plan",
            content=plan.model_dump_json(exclude_none=True),
            headers={**self.auth(self.operator), "Content-Type": "application/json"},
            timeout=60,
        )
        assert put.status_code == 200, put.text

    def device_key(self, building_id: str, device_id: str) -> str:
        response = httpx.post(
            f"{self.base}/v1/buildings/{building_id}/keys",
            json={"scope": "device", "device_id": device_id},
            headers=self.auth(self.operator),
        )
        assert response.status_code == 201, response.text
        return str(response.json()["key"])

    def counter(self, name: str, building_id: str) -> float:
        text = httpx.get(f"{self.base}/metrics").text
        for line in text.splitlines():
            if line.startswith(f'crowdslam_{name}_total{{building="{building_id}"}}'):
                return float(line.rsplit(" ", 1)[1])
        return 0.0


@pytest.fixture(scope="module")
def phone_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PhoneServer]:
    folder = tmp_path_factory.mktemp("phone")
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(folder / "data")}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    operator = migrate_with_operator_key(env)
    port = free_port()
    process = serve_process(env, port, folder / "serve.log")
    try:
        yield PhoneServer(f"http://127.0.0.1:{port}", operator, folder / "data")
    finally:
        process.terminate()
        try:
            process.wait(timeout=60)
        except Exception:
            process.kill()
            process.wait()


@pytest.fixture(scope="module")
def walk() -> Trace:
    return read_trace(WALK)


def _quaternion(row: np.ndarray) -> tuple[float, float, float, float]:
    x, y, z = (float(v) for v in row[1:4])
    return x, y, z, math.sqrt(max(0.0, 1.0 - x * x - y * y - z * z))


def _gravity(q: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """Gravity's reaction (up, 9.81 m/s^2) in the phone's frame, for the device-to-earth quaternion."""
    x, y, z, w = q
    # the third row of the rotation matrix: earth's up expressed in the device frame
    up = (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
    return tuple(9.81 * c for c in up)  # type: ignore[return-value]


class SensorPlayer:
    """A walk's accelerometer, gyroscope and rotation vector set as the browser's virtual sensors at their own
    times. ``events``: also the linear acceleration and gravity, so that ``devicemotion`` fires."""

    def __init__(self, page: Page, trace: Trace, events: bool = False) -> None:
        self.cdp: CDPSession = page.context.new_cdp_session(page)
        self.events = events
        kinds = ["accelerometer", "gyroscope", "absolute-orientation", "relative-orientation"]
        if events:
            kinds += ["linear-acceleration", "gravity"]
        for kind in kinds:
            self.cdp.send("Emulation.setSensorOverrideEnabled", {"enabled": True, "type": kind})
        rows: list[tuple[float, str, np.ndarray]] = []
        for name in ("accelerometer", "gyroscope", "rotation_vector"):
            rows += [(float(r[0]), name, r) for r in trace.streams[name]]
        rows.sort(key=lambda r: r[0])
        self.rows = rows
        self.quaternion = _quaternion(trace.streams["rotation_vector"][0])
        self.set("rotation_vector", trace.streams["rotation_vector"][0])
        self.set("accelerometer", trace.streams["accelerometer"][0])
        self.set("gyroscope", trace.streams["gyroscope"][0])

    def _xyz(self, kind: str, x: float, y: float, z: float) -> None:
        self.cdp.send(
            "Emulation.setSensorOverrideReadings",
            {"type": kind, "reading": {"xyz": {"x": x, "y": y, "z": z}}},
        )

    def set(self, name: str, row: np.ndarray) -> None:
        if name == "rotation_vector":
            self.quaternion = q = _quaternion(row)
            for kind in ("absolute-orientation", "relative-orientation"):
                self.cdp.send(
                    "Emulation.setSensorOverrideReadings",
                    {"type": kind, "reading": {"quaternion": dict(zip("xyzw", q, strict=True))}},
                )
        elif name == "accelerometer":
            x, y, z = (float(v) for v in row[1:4])
            self._xyz("accelerometer", x, y, z)
            if self.events:
                g = _gravity(self.quaternion)
                self._xyz("gravity", *g)
                self._xyz("linear-acceleration", x - g[0], y - g[1], z - g[2])
        else:
            self._xyz("gyroscope", *(float(v) for v in row[1:4]))

    def play(self, during: list[tuple[float, object]] | None = None, until_s: float | None = None) -> None:
        """Every reading at its own time from now (up to ``until_s`` into the walk); ``during``: (seconds into
        the walk, callable) run then."""
        pending = sorted(during or [], key=lambda d: d[0])
        t0 = self.rows[0][0]
        start = time.monotonic()
        for t_ms, name, row in self.rows:
            if until_s is not None and t_ms - t0 > until_s * 1000.0:
                return
            due = start + (t_ms - t0) / 1000.0
            while pending and pending[0][0] <= (t_ms - t0) / 1000.0:
                pending.pop(0)[1]()  # type: ignore[operator]
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            self.set(name, row)
        for _, action in pending:
            action()  # type: ignore[operator]
