"""Recording every accepted batch to MCAP, and replaying recordings through the ingestion path."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from schemas.estimates import Estimate
from server.recordings.recorder import BATCH_TOPIC, ESTIMATE_TOPIC, POSE_TOPIC, read_batches
from server.replay import replay_offline
from server.settings import Settings
from server.simulation.phones import simulated_batches
from slam_core.sim.simulation import Scenario, simulate
from tests.conftest import ROOT, TESTBED
from tests.server.conftest import Api, make_api

GOLDEN = ROOT / "tests" / "golden"


def small_crowd(users: int = 3, walk_m: float = 40.0) -> Scenario:
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = users
    raw["users"]["walk_length_m"] = walk_m
    return Scenario.from_dict(raw)


def test_accepted_batches_are_recorded_and_replay_to_the_same_estimates(
    sqlite_url: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    sim = simulate(small_crowd(), 2)
    receipts = []
    gen = make_api(sqlite_url, tmp_path_factory)
    api: Api = next(gen)
    api.create_building("sim")
    keys: dict[str, str] = {}
    for batch in simulated_batches(sim, "sim"):
        if batch.device_id not in keys:
            keys[batch.device_id] = api.key("sim", "device", batch.device_id)
        body = batch.model_dump_json(exclude_none=True)
        r = api.client.post(
            "/v1/buildings/sim/batches",
            content=body,
            headers={**api.auth(keys[batch.device_id]), "Content-Type": "application/json"},
        )
        assert r.status_code == 200
        receipts.append(r.json())
        if len(receipts) == 5:  # a retry is not recorded twice
            again = api.client.post(
                "/v1/buildings/sim/batches",
                content=body,
                headers={**api.auth(keys[batch.device_id]), "Content-Type": "application/json"},
            )
            assert again.json()["duplicate"]
    settings = api.settings
    with pytest.raises(StopIteration):
        next(gen)  # shuts the app down: recordings are finished
    files = sorted((settings.recordings_dir / "sim").glob("*.mcap"))
    assert len(files) == 1
    recorded = list(read_batches(files[0]))
    assert len(recorded) == len(receipts)
    with files[0].open("rb") as stream:
        topics = {channel.topic for _, channel, _ in make_reader(stream).iter_messages()}
    assert topics == {BATCH_TOPIC, ESTIMATE_TOPIC, POSE_TOPIC}
    report = replay_offline(recorded, Settings(data_dir=settings.data_dir, seed=settings.seed))
    assert report.applied == len(receipts)
    live_latest = {}
    for r in receipts:
        if r["estimate"] is not None:
            live_latest[r["estimate"]["user_id"]] = r["estimate"]
    assert set(report.latest) == set(live_latest)
    for user, estimate in report.latest.items():
        assert estimate.position.x_m == pytest.approx(live_latest[user]["position"]["x_m"], abs=1e-9)
        assert estimate.position.y_m == pytest.approx(live_latest[user]["position"]["y_m"], abs=1e-9)
    # a file cut short by a crash still yields every whole record before the cut
    cut = files[0].parent / "cut.mcap"
    data = files[0].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    partial = list(read_batches(cut))
    assert 0 < len(partial) < len(recorded)
    assert [p.raw for p in partial] == [r.raw for r in recorded[: len(partial)]]


def test_golden_recording_replays_to_its_stored_estimates() -> None:
    """tests/golden/small-crowd.mcap with seed 0 must reproduce small-crowd.json (regenerate with
    ``python tests/golden/regenerate.py`` only when a change of the estimates is intended)."""
    expected = json.loads((GOLDEN / "small-crowd.json").read_text())
    report = replay_offline(
        read_batches(GOLDEN / "small-crowd.mcap"), Settings(data_dir=Path("unused"), seed=0)
    )
    summary = report.summary()
    assert summary["batches"] == expected["batches"]
    latest = summary["latest"]
    assert isinstance(latest, dict)
    assert set(latest) == set(expected["latest"])
    for user, estimate in expected["latest"].items():
        got = latest[user]
        assert got["t_ms"] == estimate["t_ms"]
        assert got["position"]["x_m"] == pytest.approx(estimate["position"]["x_m"], abs=1e-6)
        assert got["position"]["y_m"] == pytest.approx(estimate["position"]["y_m"], abs=1e-6)


def _pose_in_frame(estimate: Estimate) -> dict[str, Any]:
    """Foxglove PoseInFrame in the building frame, written out as a dict: the formatter's oracle."""
    half = estimate.heading_rad / 2.0
    return {
        "timestamp": {"sec": estimate.t_ms // 1000, "nsec": (estimate.t_ms % 1000) * 1_000_000},
        "frame_id": f"{estimate.building_id}/{estimate.user_id}",
        "pose": {
            "position": {"x": estimate.position.x_m, "y": estimate.position.y_m, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)},
        },
    }


def test_the_formatted_pose_is_the_pose_in_frame_as_json() -> None:
    import numpy as np

    from schemas.estimates import EstimateSource
    from server.ingestion.convert import estimate
    from server.recordings.recorder import pose_in_frame_json
    from slam_core.tracking.tracker import EstimateRow

    rng = np.random.default_rng(1)
    for k in range(100):
        row = EstimateRow(1_700_000_000_123 + k, *rng.normal(0, 50, 2), (1.0, 0.0, 1.0), (0.0, 0.0), k * 0.37)
        e = estimate(row, "hq", f"user-{k}", "phone", None, EstimateSource.DYNAMICSLAM)
        assert json.loads(pose_in_frame_json(e)) == _pose_in_frame(e)
    assert math.isclose(
        json.loads(pose_in_frame_json(e))["pose"]["orientation"]["w"], math.cos(e.heading_rad / 2)
    )
