"""Recording every accepted batch to MCAP, and replaying recordings through the ingestion path."""

from __future__ import annotations

import json
import math
import os
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from schemas.estimates import Estimate
from server.recordings.recorder import (
    BATCH_TOPIC,
    ESTIMATE_TOPIC,
    POSE_TOPIC,
    BuildingRecorder,
    Pruned,
    prune_recordings,
    read_batches,
)
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


def test_a_recording_is_compressed_in_chunks_and_a_file_cut_short_reads_to_its_last_whole_chunk(
    tmp_path: Path,
) -> None:
    """Records go in zstd chunks: a file cut short by a crash still yields every batch of its whole chunks
    before the cut, in order; the recording is several times smaller than the batches it holds."""
    recorder = BuildingRecorder(tmp_path, "b", chunk_bytes=16_384, flush_s=3600.0)
    bodies = [
        json.dumps({"batch_id": f"phone-{k}", "seq": k, "steps": [k] * 40}).encode() for k in range(2_000)
    ]
    for k, body in enumerate(bodies):
        recorder.record_batch(body, 1_800_000_000_000_000_000 + k)
        recorder.flush()  # within the hour's flush period: chunks are written as they fill
    recorder.close()
    (path,) = (tmp_path / "b").glob("*.mcap")
    assert [r.raw for r in read_batches(path)] == bodies
    assert path.stat().st_size < sum(len(b) for b in bodies) / 4
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 3])  # amid the chunks (the summary after them is a good part)
    partial = [r.raw for r in read_batches(cut)]
    assert 0 < len(partial) < len(bodies)
    assert partial == bodies[: len(partial)]


def test_old_and_surplus_recordings_are_deleted_whole_oldest_first(tmp_path: Path) -> None:
    now = datetime(2026, 12, 6, 12, 30, tzinfo=UTC).timestamp()

    def recording(building: str, hours_ago: float, size: int, name: str) -> Path:
        path = tmp_path / building / f"{name}.mcap"
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(b"x" * size)
        os.utime(path, (now - 3600 * hours_ago, now - 3600 * hours_ago))  # age is the last write
        return path

    # a replay writes old hours now: the name's hour does not count
    current = recording("a", 0.2, 500, "20200101T00")  # being written: never deleted
    old = [recording("a", 60, 100, "20261204T00"), recording("b", 55, 100, "20261204T05-1")]
    mid = [recording("b", 10, 100, "20261206T02"), recording("a", 5, 100, "20261206T07")]
    recent = recording("b", 1.5, 100, "20261206T11")
    (tmp_path / "a" / "notes.txt").write_text("not a recording")
    assert prune_recordings(tmp_path, 3 * 86_400, None, now) == Pruned(0, 0)  # none is three days old
    assert prune_recordings(tmp_path, 48 * 3600, None, now) == Pruned(2, 200)
    assert not any(p.exists() for p in old)
    assert prune_recordings(tmp_path, None, 150, now) == Pruned(2, 200)  # oldest first, to fit
    assert not any(p.exists() for p in mid)
    assert recent.exists()
    assert current.exists()
    assert (tmp_path / "a" / "notes.txt").exists()
    assert prune_recordings(tmp_path, None, 0, now) == Pruned(1, 100)
    assert current.exists()
    assert prune_recordings(tmp_path, 60.0, 0, now) == Pruned(0, 0)  # the last hour stays whatever the limits


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
    """Foxglove PoseInFrame in the building frame, to the millimetre, written out as a dict: the formatter's
    oracle."""
    half = estimate.heading_rad / 2.0
    return {
        "timestamp": {"sec": estimate.t_ms // 1000, "nsec": (estimate.t_ms % 1000) * 1_000_000},
        "frame_id": f"{estimate.building_id}/{estimate.user_id}",
        "pose": {
            "position": {
                "x": round(estimate.position.x_m, 3),
                "y": round(estimate.position.y_m, 3),
                "z": 0.0,
            },
            "orientation": {"x": 0.0, "y": 0.0, "z": round(math.sin(half), 5), "w": round(math.cos(half), 5)},
        },
    }


def _rounded(value: Any, key: str = "") -> Any:
    """The estimate's JSON as recorded, rounded by its fields' units: the formatter's oracle."""
    if isinstance(value, dict):
        return {k: _rounded(v, k) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v, key) for v in value]
    if isinstance(value, float):
        digits = {"covariance_m2": 6, "heading_rad": 4, "lat_deg": 8, "lon_deg": 8}.get(key, 3)
        return round(value, digits)
    return value


def _estimates(n: int) -> list[Estimate]:
    import numpy as np

    from schemas.estimates import EstimateSource
    from server.ingestion.convert import estimate
    from slam_core.tracking.tracker import EstimateRow

    rng = np.random.default_rng(1)
    out = []
    for k in range(n):
        xx, yy = float(rng.uniform(1e-4, 9.0)), float(rng.uniform(1e-4, 4.0))
        cov = (xx, float(rng.uniform(-0.9, 0.9)) * math.sqrt(xx * yy), yy)
        best = (float(rng.normal(0, 50)), float(rng.normal(0, 50)))
        row = EstimateRow(1_700_000_000_123 + k, *rng.normal(0, 50, 2), cov, best, k * 0.37)
        e = estimate(row, "hq", f"user-{k}", "phone", None, EstimateSource.DYNAMICSLAM)
        if k % 2:
            e = e.model_copy(
                update={"lat_deg": float(rng.uniform(-90, 90)), "lon_deg": float(rng.uniform(-180, 180))}
            )
        if k % 3 == 0:
            e = e.model_copy(update={"best_particle": None})
        out.append(e)
    return out


def test_the_formatted_pose_is_the_pose_in_frame_as_json() -> None:
    from server.recordings.recorder import pose_in_frame_json

    for e in _estimates(100):
        assert json.loads(pose_in_frame_json(e)) == _pose_in_frame(e)


def test_a_recorded_estimate_is_the_estimate_to_the_millimetre() -> None:
    from server.recordings.recorder import estimate_json

    for e in _estimates(100):
        recorded = estimate_json(e)
        assert json.loads(recorded) == _rounded(e.model_dump(mode="json"))
        back = Estimate.model_validate_json(recorded)  # valid against the channel's schema
        assert abs(back.position.x_m - e.position.x_m) <= 5e-4
        assert back.best_particle is None if e.best_particle is None else back.best_particle is not None
        assert len(recorded) < len(e.model_dump_json())
