"""import-msindoor writes a recording a replay can read; replay --offline reports what it applied."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from server.cli.main import main
from server.recordings.recorder import read_batches
from tests.conftest import ROOT, SAMPLE_FLOOR

pytestmark = pytest.mark.walks

WALKS = SAMPLE_FLOOR / "path_data_files"


def test_import_msindoor_records_every_batch_of_every_walk(tmp_path: Path) -> None:
    smallest = sorted(WALKS.glob("*.txt"), key=lambda p: p.stat().st_size)[:2]
    folder = tmp_path / "walks"
    folder.mkdir()
    for walk in smallest:
        shutil.copy(walk, folder / walk.name)
    out = tmp_path / "f1.mcap"
    assert main(["import-msindoor", str(folder), "--out", str(out)]) == 0
    batches = [json.loads(b.raw) for b in read_batches(out)]
    devices = {b["device_id"] for b in batches}
    assert len(devices) == 2
    for device in devices:
        seqs = [b["seq"] for b in batches if b["device_id"] == device]
        assert seqs == list(range(len(seqs)))


def test_import_msindoor_writes_the_floor_plan_beside_the_recording(tmp_path: Path) -> None:
    """The data set's map in the local frame: its outline walkable, its shops obstacles; the surveyed
    waypoints of a walk lie in the walkable area."""
    from schemas.floor_plans import FloorPlan, PlanKind
    from server.datasets.msindoor import read_trace
    from server.ingestion.floor_plans import engine_plan

    floor = tmp_path / "F1"
    (floor / "path_data_files").mkdir(parents=True)
    for name in ("floor_info.json", "geojson_map.json"):
        shutil.copy(SAMPLE_FLOOR / name, floor / name)
    smallest = sorted(WALKS.glob("*.txt"), key=lambda p: p.stat().st_size)[0]
    shutil.copy(smallest, floor / "path_data_files" / smallest.name)
    out = tmp_path / "f1.mcap"
    assert main(["import-msindoor", str(floor), "--out", str(out)]) == 0
    plan = FloorPlan.model_validate_json((tmp_path / "f1.plan.json").read_text())
    kinds = [f.properties.kind for f in plan.features]
    assert kinds.count(PlanKind.WALKABLE) == 1
    assert kinds.count(PlanKind.OBSTACLE) > 100
    waypoints = read_trace(smallest).waypoints
    assert engine_plan(plan).walkable(waypoints[:, 1:]).all()


def test_replay_offline_of_the_golden_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "replay.json"
    code = main(
        ["replay", str(ROOT / "tests" / "golden" / "small-crowd.mcap"), "--offline", "--json", str(out)]
    )
    assert code == 0
    summary = json.loads(out.read_text())
    assert summary["applied"] == summary["batches"] > 50
    assert summary["rejected"] == 0
    assert main(["replay", str(tmp_path / "missing.mcap"), "--offline"]) == 2
