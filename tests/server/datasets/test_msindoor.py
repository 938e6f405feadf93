"""The Indoor Location 2.0 reader on real walks (the sample's, and whole floors where they are) and on broken
files."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from schemas.floor_plans import FLOOR_PLAN_EXAMPLE, FloorPlan, PlanKind
from server.datasets.msindoor import TraceFormatError, read_floor, read_floor_plan, read_trace, shop_frontages
from server.datasets.msindoor_batches import trace_batches
from server.ingestion.floor_plans import engine_plan
from slam_core.zones.geometry import ring_problem
from tests.conftest import SAMPLE_FLOOR, whole_floor

pytestmark = pytest.mark.walks

FLOOR = SAMPLE_FLOOR
SMALL_WALK = FLOOR / "path_data_files" / "5dd9e7c59191710006b57065.txt"


def _count(path: Path, kind: str) -> int:
    return sum(
        1 for line in path.read_text().splitlines() if not line.startswith("#") and f"\t{kind}\t" in line
    )


def test_floor_metadata() -> None:
    floor = read_floor(whole_floor("site1/F1"))
    assert floor.width_m == pytest.approx(239.8175, abs=1e-3)
    assert floor.height_m == pytest.approx(176.4412, abs=1e-3)
    assert floor.image is not None
    assert floor.geojson["type"] == "FeatureCollection"
    assert len(floor.traces) > 90


def test_every_record_type_of_a_real_walk_is_read() -> None:
    trace = read_trace(SMALL_WALK)
    assert trace.header["FloorName"] == "F1"
    assert trace.header["Model"] == "PBCM10"
    accel = trace.streams["accelerometer"]
    assert len(accel) == _count(SMALL_WALK, "TYPE_ACCELEROMETER")
    assert np.all(np.diff(accel[:, 0]) > 0)
    assert trace.streams["gyroscope_uncalibrated"].shape[1] == 7
    assert sum(len(s.bssid) for s in trace.wifi) <= _count(SMALL_WALK, "TYPE_WIFI")
    assert len(trace.beacons) == _count(SMALL_WALK, "TYPE_BEACON")
    assert len(trace.ble) == _count(SMALL_WALK, "TYPE_BLUE")
    assert len(trace.blu4) == _count(SMALL_WALK, "TYPE_BLU4")
    assert trace.dist1.shape == (1, 4)
    assert trace.dist2.shape == (1, 4)
    assert len(trace.magnetic_accuracy_changes) == 1
    assert np.all(np.diff(trace.waypoints[:, 0]) > 0)  # the repeated last waypoint is dropped
    assert trace.end_ms > trace.start_ms


def test_batches_cover_every_sample_once_and_validate() -> None:
    trace = read_trace(SMALL_WALK)
    batches = list(trace_batches(trace, "site1", "walker"))
    assert [b.seq for b in batches] == list(range(len(batches)))
    assert len({b.batch_id for b in batches}) == len(batches)
    accel_times = [t for b in batches if b.accelerometer for t in b.accelerometer.t_ms]
    assert accel_times == trace.streams["accelerometer"][:, 0].astype(int).tolist()
    spans = [b.time_span_ms() for b in batches]
    assert all(span is not None and span[1] - span[0] < 1000 for span in spans)
    assert sum(len(b.wifi_scans) for b in batches) == len(trace.wifi)


def test_cached_wifi_entries_keep_their_last_seen_time() -> None:
    trace = read_trace(SMALL_WALK)
    ages = np.concatenate([s.t_ms - s.last_seen_ms for s in trace.wifi])
    assert np.mean(ages > 3000) > 0.2  # re-reported cached APs are common (50-60 % on this floor)


def test_lines_out_of_time_order_are_sorted(tmp_path: Path) -> None:
    path = tmp_path / "walk.txt"
    path.write_text(
        "#\tstartTime:1574559495255\n"
        "1574559495421\tTYPE_ACCELEROMETER\t0.1\t0.2\t9.8\t3\n"
        "1574559495401\tTYPE_ACCELEROMETER\t0.0\t0.1\t9.7\t3\n"
        "1574559495401\tTYPE_ACCELEROMETER\t0.0\t0.1\t9.7\t3\n"
        "1574559499000\tTYPE_WAYPOINT\t2.0\t3.0\n"
        "1574559495300\tTYPE_WAYPOINT\t1.0\t1.0\n"
        "#\tendTime:1574559499999\n"
    )
    trace = read_trace(path)
    np.testing.assert_array_equal(trace.streams["accelerometer"][:, 0], [1574559495401, 1574559495421])
    np.testing.assert_array_equal(trace.waypoints[:, 1], [1.0, 2.0])


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1574559495401\tTYPE_ACCELEROMETER\t0.1\t0.2\n", "needs 6 columns, found 4"),
        ("1574559495401\tTYPE_ACCELEROMETER\t0.1\tabc\t9.8\t3\n", "bad TYPE_ACCELEROMETER value"),
        ("1574559495401\tTYPE_TELEPORT\t1\n", "unknown record type 'TYPE_TELEPORT'"),
        ("not-a-time\tTYPE_WAYPOINT\t1.0\t2.0\n", "bad TYPE_WAYPOINT value"),
    ],
)
def test_malformed_lines_name_the_file_and_line(tmp_path: Path, line: str, message: str) -> None:
    path = tmp_path / "broken.txt"
    path.write_text("#\tstartTime:1574559495255\n1574559495300\tTYPE_WAYPOINT\t1.0\t1.0\n" + line)
    with pytest.raises(TraceFormatError, match=message) as caught:
        read_trace(path)
    assert caught.value.line == 3
    assert str(path) in str(caught.value)


def test_missing_floor_info_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(TraceFormatError, match=r"floor_info\.json"):
        read_floor(tmp_path)


@pytest.mark.parametrize("name", ["site1/F1", "site2/F2"])
def test_a_shipped_floors_map_becomes_a_plan_holding_its_surveyed_waypoints(name: str) -> None:
    floor_dir = whole_floor(name)
    floor = read_floor(floor_dir)
    reading = read_floor_plan(floor)
    assert (reading.skipped_features, reading.repaired_rings, reading.dropped_rings) == (0, 0, 0)
    assert reading.plan is not None
    kinds = [f.properties.kind for f in reading.plan.features]
    assert kinds.count(PlanKind.WALKABLE) == 1
    assert len(kinds) == len(json.loads((floor_dir / "geojson_map.json").read_text())["features"])
    index = engine_plan(reading.plan)
    waypoints = np.concatenate([read_trace(p).waypoints[:, 1:3] for p in floor.traces[::8]])
    assert waypoints.shape[0] > 20
    assert index.walkable(waypoints).all()
    assert not index.walkable(np.array([[-5.0, -5.0], [floor.width_m + 5, floor.height_m + 5]])).any()


def _write_map(tmp_path: Path, features: Sequence[object]) -> Path:
    (tmp_path / "floor_info.json").write_text(json.dumps({"map_info": {"width": 100.0, "height": 50.0}}))
    (tmp_path / "geojson_map.json").write_text(
        json.dumps({"type": "FeatureCollection", "features": features})
    )
    return tmp_path


def _polygon(*rings: list[list[float]]) -> dict[str, object]:
    return {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": list(rings)}}


def test_a_hand_drawn_maps_flaws_are_repaired_or_left_out_and_counted(tmp_path: Path) -> None:
    outline = [[10.0, 20.0], [30.0, 20.0], [30.0, 30.0], [10.0, 30.0]]  # open: closed by the reader
    shop = [[12.0, 22.0, 3.0], [14.0, 22.0, 3.0], [14.0, 24.0, 3.0], [12.0, 22.0, 3.0]]  # with altitudes
    features: list[object] = [
        _polygon(outline),
        _polygon(shop),
        _polygon(
            [[20.0, 25.0], [20.0, 25.0], [21.0, 25.0], [20.0, 25.0]], [[20.0, 25.0], [21, 26], [21, 25]]
        ),
        {"type": "Feature", "properties": {"name": "kiosk"}, "geometry": None},
        {"type": "Feature", "properties": {}, "geometry": {"type": "Point", "coordinates": [15.0, 25.0]}},
        {"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [[["a", 1], [1, 2], [2, 2]]]}},
        "not a feature",
    ]
    reading = read_floor_plan(read_floor(_write_map(tmp_path, features)))
    assert reading.skipped_features == 4  # null, point, non-numeric ring, degenerate polygon with its hole
    assert reading.repaired_rings == 1
    assert reading.dropped_rings == 3  # the degenerate outer ring, its hole, the non-numeric ring
    assert reading.plan is not None
    walkable, obstacle = reading.plan.features
    assert walkable.properties.kind == "walkable"
    assert obstacle.properties.kind == "obstacle"
    # the outline's bounds span the floor: (10, 20) -> (0, 0) and (30, 30) -> (100, 50)
    assert next(iter(walkable.rings())) == [(0.0, 0.0), (100.0, 0.0), (100.0, 50.0), (0.0, 50.0), (0.0, 0.0)]
    assert next(iter(obstacle.rings()))[:2] == [(10.0, 10.0), (20.0, 10.0)]
    index = engine_plan(reading.plan)
    assert index.walkable(np.array([[50.0, 25.0]])).all()


@pytest.mark.parametrize(
    "features",
    [
        [],
        [{"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]}}],
        [_polygon([[5.0, 5.0], [5.0, 6.0], [5.0, 7.0], [5.0, 5.0]])],  # an outline with no area
    ],
    ids=["no features", "no polygon", "flat outline"],
)
def test_a_map_without_a_usable_outline_gives_no_plan(
    tmp_path: Path, features: list[dict[str, object]]
) -> None:
    assert read_floor_plan(read_floor(_write_map(tmp_path, features))).plan is None


def test_a_shops_frontage_is_the_shop_grown_by_its_reach() -> None:
    plan = FloorPlan.model_validate(FLOOR_PLAN_EXAMPLE)
    [(name, ring)] = shop_frontages(plan, 4.0)  # the cafe alone: the outline is walkable, the wall a line
    assert name == "Cafe"
    assert ring_problem(ring) is None
    lo, hi = ring.min(axis=0), ring.max(axis=0)
    np.testing.assert_allclose([*lo, *hi], [6.0, 6.0, 24.0, 22.0], atol=0.01)
    # its area: the 10 x 8 m cafe, four 4 m strips along its sides, and corners between a square's and a
    # quarter circle's (quad_segs=2 cuts each corner's arc in two chords)
    area = 0.5 * abs(
        np.dot(ring[:, 0], np.roll(ring[:, 1], -1)) - np.dot(ring[:, 1], np.roll(ring[:, 0], -1))
    )
    assert 80 + 4 * (2 * 10 + 2 * 8) + 4 * (np.pi * 16 / 4) * 0.85 < area < 80 + 4 * 36 + 4 * 16
