"""With ``CROWDSLAM_COLD_START``, a phone that posts scans but no fix is placed by its building's radio map
(loaded from the latest finished signal-map build when the building loads): its receipts say ``tracking``
and carry an estimate only once it is placed."""

from __future__ import annotations

import math
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from schemas.signal_maps import SignalMapJob, SignalMapStatus
from server.app import create_app
from server.ingestion.radio_maps import RECORD, write_radio_map
from server.settings import Settings
from tests.server.conftest import Api, migrate_with_operator

T0 = 1_767_225_600_000
APS = [(x, y) for x in np.linspace(0, 80, 9) for y in (-4.0, 4.0)]
NAMES = [f"0a:00:00:00:02:{i:02x}" for i in range(len(APS))]


def _aps(xy: np.ndarray, rng: np.random.Generator) -> dict[str, float]:
    d = np.hypot(*(np.asarray(APS) - xy).T)
    rss = -40.0 - 25.0 * np.log10(np.maximum(d, 1.0)) + rng.normal(0, 2.0, d.size)
    return {n: round(float(r), 1) for n, r in zip(NAMES, rss, strict=True) if r > -90.0}


@pytest.fixture
def cold_api(tmp_path: Path) -> Iterator[Api]:
    """A building whose data folder holds a finished build's radio map of an 80 m corridor."""
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    rng = np.random.default_rng(0)
    folder = tmp_path / "signal_maps" / "hq" / "build1"
    folder.mkdir(parents=True)
    xs = np.arange(0.0, 80.0, 1.0)  # 80 scans: more than the map needs before it places anyone (50)
    write_radio_map(
        folder,
        np.column_stack([xs, 0 * xs]),
        [_aps(np.array([x, 0.0]), rng) for x in xs],
        T0 - 3_600_000 + 0 * xs,
        np.zeros(xs.size, dtype=np.int64),
    )
    job = SignalMapJob(
        id="build1", building_id="hq", status=SignalMapStatus.DONE, created_at=datetime.now(UTC), recordings=1
    )
    (folder / RECORD).write_text(job.model_dump_json())
    settings = Settings(data_dir=tmp_path, database_url=url, cold_start=True)
    with TestClient(create_app(settings)) as client:
        yield Api(client, operator, url, settings)


def _second(k: int, x: float, rng: np.random.Generator) -> dict[str, Any]:
    t = T0 + 1000 * k
    return {
        "building_id": "hq",
        "device_id": "walker",
        "batch_id": f"walker-{k}",
        "seq": k,
        "steps": [{"t_ms": t + 250 + 500 * j, "length_m": 0.7, "azimuth_rad": math.pi / 2} for j in range(2)],
        "wifi_scans": [
            {
                "t_ms": t + 500,
                "aps": [
                    {"bssid": b, "rssi_dbm": r, "frequency_mhz": 2412}
                    for b, r in _aps(np.array([x, 0.0]), rng).items()
                ],
            }
        ],
    }


def test_a_phone_without_a_fix_is_placed_by_the_buildings_radio_map(cold_api: Api) -> None:
    api = cold_api
    api.create_building(size_m=(80.0, 20.0))
    key = api.key("hq", "device", "walker")
    rng = np.random.default_rng(1)
    receipts, x = [], 10.0
    for k in range(30):
        x += 1.4
        response = api.client.post("/v1/buildings/hq/batches", json=_second(k, x, rng), headers=api.auth(key))
        assert response.status_code == 200, response.text
        receipts.append(response.json())
    tracked = [r["tracking"] for r in receipts]
    assert True in tracked  # placed, with no fix ever sent
    placed_at = tracked.index(True)
    assert all(tracked[placed_at:])
    assert all(r["estimate"] is None for r in receipts[:placed_at])  # nothing reported before
    last = receipts[-1]["estimate"]
    assert abs(last["position"]["x_m"] - x) < 5.0
    worker: Any = api.client.app.state.crowdslam.tracking.handles["hq"]  # type: ignore[attr-defined]
    assert worker.host.tracker.radio_map_id == "build1"  # loaded with the building
