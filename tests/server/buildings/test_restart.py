"""Crash recovery: a building's session abandoned mid-walk (as by ``kill -9``) is rebuilt from its last
snapshot plus the batch log, bit for bit, and tracking resumes; a snapshot that cannot be used is refused
and the building falls back to its SQL anchor map."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import Engine, func, select

from schemas.anchors import KnownAnchorIn
from schemas.common import Position
from schemas.live import ZoneMessage
from schemas.sensors import SensorBatch
from schemas.zones import ZoneIn, ZonePolygon
from server.buildings.config import Retention, TrackingConfig
from server.buildings.host import BuildingHost
from server.buildings.submissions import Submission
from server.settings import Settings
from server.simulation.phones import KnownAnchor, known_anchors, simulated_batches
from server.slam.config import load_calibration, tracker_params
from server.store import repositories as repo
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade
from server.store.models import BatchLogRow, BatchRow, BuildingRow, TrackerSnapshotRow
from slam_core.sim.simulation import Scenario, simulate
from tests.conftest import TESTBED

SETTINGS = Settings(seed=5)


def _crowd() -> tuple[list[Submission], list[KnownAnchor]]:
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = 5
    raw["users"]["walk_length_m"] = 50.0
    sim = simulate(Scenario.from_dict(raw), 2)
    batches = list(simulated_batches(sim, "hq"))
    return [Submission.of(b, b.model_dump_json().encode(), 0) for b in batches], known_anchors(sim)


CROWD, KNOWN = _crowd()


def _groups(subs: list[Submission], size: int = 4) -> list[list[Submission]]:
    return [subs[i : i + size] for i in range(0, len(subs), size)]


def _building(
    engine: Engine,
    snapshot_period_s: float = math.inf,
    n_particles: int | None = None,
    retention: Retention | None = None,
) -> BuildingHost:
    tp = tracker_params(SETTINGS)
    if n_particles is not None:
        tp = replace(tp, filter=replace(tp.filter, n_particles=n_particles))
    config = TrackingConfig(
        tp, load_calibration(None), SETTINGS.seed, snapshot_period_s, retention or Retention()
    )
    return BuildingHost("hq", make_session_factory(engine), config)


def _fresh_building(url: str) -> Engine:
    engine = make_engine(url)
    upgrade(engine)
    with make_session_factory(engine).begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
    return engine


def _pin_known(session: BuildingHost) -> None:
    for k, anchor in enumerate(KNOWN):
        body = KnownAnchorIn(
            type=anchor.type, position=Position(x_m=anchor.position[0], y_m=anchor.position[1])
        )
        session.anchor_edits.put_known(f"known-{k}", body)


def _estimates(session: BuildingHost) -> dict[str, object]:
    return {u: session.building.latest_estimate(u) for u in session.tracker.users}


def _logged(engine: Engine) -> int:
    with make_session_factory(engine)() as s:
        return int(s.execute(select(func.count()).select_from(BatchLogRow)).scalar_one())


def _logged_after(engine: Engine, tracker_call: int) -> int:
    with make_session_factory(engine)() as s:
        return int(s.execute(select(func.count()).where(BatchRow.tracker_call > tracker_call)).scalar_one())


def _snapshot_call(engine: Engine) -> int:
    with make_session_factory(engine)() as s:
        return int(s.execute(select(TrackerSnapshotRow.tracker_call)).scalar_one())


@pytest.mark.parametrize("snapshot_period_s", [math.inf, 0.0])
def test_an_abandoned_building_is_rebuilt_exactly_and_tracking_resumes(
    database_url: str, sqlite_url: str, snapshot_period_s: float
) -> None:
    groups = _groups(CROWD)
    cut = len(groups) * 3 // 5
    # the reference: one session that never stops, in its own database
    reference_engine = _fresh_building(sqlite_url.replace(".sqlite3", "-ref.sqlite3"))
    reference = _building(reference_engine)
    _pin_known(reference)
    for group in groups[:cut]:
        reference.process(group)
    at_crash = _estimates(reference)

    engine = _fresh_building(database_url)
    crashed = _building(engine, snapshot_period_s)
    _pin_known(crashed)
    for group in groups[:cut]:
        crashed.process(group)
    assert _estimates(crashed) == at_crash
    applied_since_snapshot = _logged_after(engine, _snapshot_call(engine))
    if snapshot_period_s == 0.0:
        # a snapshot taken at every chance: compressed in the background and written by a later group; the
        # batches applied after the one written last are logged (and maybe some it covers, cleared a chunk
        # per group, but never replayed)
        assert crashed.counters.snapshots >= 2
        assert _logged(engine) >= applied_since_snapshot
        assert applied_since_snapshot < sum(len(g) for g in groups[:cut])
    else:
        assert _logged(engine) == applied_since_snapshot == sum(len(g) for g in groups[:cut])
    anchors_at_crash = crashed.anchor_edits.anchors()
    del crashed  # no shutdown, no final snapshot: as after kill -9

    restarted = _building(engine, snapshot_period_s)
    assert restarted.restore_problem is None
    assert restarted.counters.replayed == applied_since_snapshot
    assert _estimates(restarted) == at_crash
    assert restarted.anchor_edits.anchors() == anchors_at_crash
    assert _logged(engine) == 0  # the load snapshot covers the replayed log

    for group in groups[cut:]:
        reference.process(group)
        receipts = restarted.process(group).receipts
        assert all(getattr(r, "status", None) == "applied" for r in receipts)
    assert _estimates(restarted) == _estimates(reference)
    assert all(restarted.tracker.is_tracking(u) for u in restarted.tracker.users)
    reference_engine.dispose()
    engine.dispose()


def test_a_snapshot_compressed_in_the_background_covers_its_own_engine_calls_only(sqlite_url: str) -> None:
    """Taken by one group, written by a later one: the batches applied in between stay logged, and a crash
    while a snapshot is being compressed restarts from the one before it and the whole log."""
    g0, g1, g2, g3 = _groups(CROWD)[:4]
    reference = _building(_fresh_building(sqlite_url.replace(".sqlite3", "-ref.sqlite3")))
    for group in (g0, g1, g2, g3):
        reference.process(group)
    engine = _fresh_building(sqlite_url)
    session = _building(engine, snapshot_period_s=0.0)
    loaded_call = _snapshot_call(engine)
    session.process(g0)  # takes a snapshot: compressed in the background, nothing written yet
    assert _snapshot_call(engine) == loaded_call
    assert _logged(engine) == len(g0)
    taken_at = session.building.tracker_call
    session.recovery.wait()
    session.process(g1)  # writes it: g0 is covered, g1 is not
    assert _snapshot_call(engine) == taken_at
    assert _logged(engine) == len(g1) == _logged_after(engine, taken_at)
    session.process(g2)  # takes the next one
    session.process(g3)  # which may or may not be written yet: either way a restart is exact
    del session  # as after kill -9
    restarted = _building(engine, snapshot_period_s=0.0)
    assert restarted.restore_problem is None
    assert restarted.counters.replayed == _logged_after(
        engine, taken_at
    ) or restarted.counters.replayed == len(g3)
    assert _estimates(restarted) == _estimates(reference)


def test_a_log_cleared_slower_than_it_grows_replays_after_the_snapshots_call_only(sqlite_url: str) -> None:
    """Covered bodies are cleared a chunk per group; when that is slower than the log grows, some stay. A
    crash then replays only the batches applied after the snapshot's tracker call, and the restart is
    exact."""
    groups = _groups(CROWD)[:10]
    reference = _building(_fresh_building(sqlite_url.replace(".sqlite3", "-ref.sqlite3")))
    for group in groups:
        reference.process(group)
    engine = _fresh_building(sqlite_url)
    # two bodies cleared a group of four: slower than the log grows
    session = _building(engine, snapshot_period_s=0.0, retention=Retention(log_clear_per_batch=0.5))
    for group in groups:
        session.process(group)
        session.recovery.wait()
    after_snapshot = _logged_after(engine, _snapshot_call(engine))
    assert session.counters.log_bodies_cleared > 0
    assert _logged(engine) > after_snapshot  # covered bodies not cleared yet
    del session  # as after kill -9
    restarted = _building(engine, snapshot_period_s=0.0)
    assert restarted.restore_problem is None
    assert restarted.counters.replayed == after_snapshot
    assert _estimates(restarted) == _estimates(reference)
    assert _logged(engine) == 0  # the load snapshot covers the whole log


def test_a_retried_batch_after_restart_is_still_a_duplicate(sqlite_url: str) -> None:
    engine = _fresh_building(sqlite_url)
    session = _building(engine)
    _pin_known(session)
    first = _groups(CROWD)[0]
    session.process(first)
    restarted = _building(engine)
    receipts = restarted.process(first).receipts
    assert [getattr(r, "status", None) for r in receipts] == ["duplicate"] * len(first)
    assert restarted.counters.replayed == len(first)
    engine.dispose()


@pytest.mark.parametrize("other_parameters", [False, True])
def test_a_batch_older_than_the_logged_ones_is_late_after_a_restart(
    sqlite_url: str, other_parameters: bool
) -> None:
    """Devices' last sequence numbers reach SQL with snapshots; after a crash the batch log supplies the
    newer ones, also when the snapshot is refused and the filters start again."""
    engine = _fresh_building(sqlite_url)
    session = _building(engine)  # snapshots only on load: every group below stays in the log
    for group in _groups(CROWD)[:6]:
        session.process(group)
    last = {s.header.device_id: s.header.seq for g in _groups(CROWD)[:6] for s in g}
    device, seq = next(iter(last.items()))
    restarted = _building(engine, n_particles=40 if other_parameters else None)
    assert (restarted.restore_problem is not None) == other_parameters
    old = next(
        SensorBatch.model_validate_json(s.raw)
        for s in CROWD
        if s.header.device_id == device and s.header.seq == seq - 1
    )
    resent = old.model_copy(update={"batch_id": f"{old.batch_id}-again"})
    receipt = restarted.process([Submission.of(resent, resent.model_dump_json().encode(), 0)]).receipts[0]
    assert getattr(receipt, "status", None) == "late"
    engine.dispose()


def test_a_snapshot_taken_with_other_parameters_is_refused_and_the_sql_map_is_kept(sqlite_url: str) -> None:
    engine = _fresh_building(sqlite_url)
    session = _building(engine)
    _pin_known(session)
    for group in _groups(CROWD)[:20]:
        session.process(group)
    anchors = {a.id: a for a in session.anchor_edits.anchors()}
    other = _building(engine, n_particles=40)
    assert other.restore_problem == "snapshot was taken with other tracker parameters"
    assert other.counters.restore_failures == 1
    assert other.counters.replayed == 0
    assert other.tracker.users == []  # users start again from their next fix
    assert _logged(engine) == 0  # the load snapshot covers the log it did not replay
    other.process(_groups(CROWD)[20])
    assert _logged_after(engine, _snapshot_call(engine)) == len(_groups(CROWD)[20])
    restored = {a.id: a for a in other.anchor_edits.anchors()}
    assert restored.keys() == anchors.keys()
    for public_id, anchor in anchors.items():
        assert restored[public_id].position == anchor.position
        assert restored[public_id].known == anchor.known
    engine.dispose()


def test_the_batch_path_prunes_history_but_keeps_every_users_latest_position(sqlite_url: str) -> None:
    from server.store.models import PositionSnapshotRow

    engine = _fresh_building(sqlite_url)
    session = _building(
        engine,
        retention=Retention(
            position_history_days=1e-12,
            position_history_period_s=0.0,
            batch_ids_hours=None,
            prune_period_s=0.0,
        ),
    )
    groups = _groups(CROWD)[:12]
    for group in groups:
        session.process(group)
    with make_session_factory(engine)() as s:
        history = int(s.execute(select(func.count()).select_from(PositionSnapshotRow)).scalar_one())
        latest = {r.user_id: r.t_ms for r in repo.latest_positions(s, "hq")}
        batches = int(s.execute(select(func.count()).select_from(BatchRow)).scalar_one())
    assert session.counters.pruned_positions > 0
    assert history == session.counters.estimates - session.counters.pruned_positions
    assert set(latest) == set(session.tracker.users)
    assert all(latest[u] == session.building.latest_estimate(u).t_ms for u in latest)  # type: ignore[union-attr]
    assert batches == sum(len(g) for g in groups)  # batch ids kept: None keeps them all
    engine.dispose()


def test_the_history_keeps_one_estimate_a_period_and_the_latest_position_every_batch(sqlite_url: str) -> None:
    """``position_history_period_s``: a user's history rows are at least the period apart in the phone's time
    (the first estimate of each period kept), while its latest position follows every batch."""
    from server.store.models import PositionSnapshotRow

    engine = _fresh_building(sqlite_url)
    building = _building(engine, retention=Retention(position_history_period_s=3.0))
    for group in _groups(CROWD)[:16]:
        building.process(group)
    with make_session_factory(engine)() as s:
        rows = s.execute(select(PositionSnapshotRow.user_id, PositionSnapshotRow.t_ms)).all()
        latest = {r.user_id: r.t_ms for r in repo.latest_positions(s, "hq")}
    by_user: dict[str, list[int]] = {}
    for user, t in rows:
        by_user.setdefault(user, []).append(t)
    assert 0 < len(rows) < building.counters.estimates / 2  # a batch a second, a row every 3 s
    for user, times in by_user.items():
        times.sort()
        assert all(b - a >= 3_000 for a, b in itertools.pairwise(times)), user
        assert latest[user] == building.building.latest_estimate(user).t_ms >= times[-1]  # type: ignore[union-attr]
    engine.dispose()


def test_idle_users_are_forgotten_at_a_snapshot_and_stay_forgotten_after_a_restart(sqlite_url: str) -> None:

    engine = _fresh_building(sqlite_url)

    def session() -> BuildingHost:
        return _building(engine, retention=Retention(user_idle_s=1e-9))

    first = session()
    everywhere = [[-1e4, -1e4], [1e4, -1e4], [1e4, 1e4], [-1e4, 1e4], [-1e4, -1e4]]
    zone = ZoneIn(floor=0, name="all", polygon=ZonePolygon(type="Polygon", coordinates=[everywhere]))
    first.zones.put("all", zone)
    groups = _groups(CROWD)
    for group in groups[:8]:
        first.process(group)
    users = len(first.tracker.users)
    assert users > 0
    with make_session_factory(engine)() as s:
        inside = {v.user_id for v in repo.open_visits(s, "hq")}
        latest = {r.user_id: r.t_ms for r in repo.latest_positions(s, "hq")}
    assert inside == set(latest)  # every placed user is in the zone
    first.snapshot()  # everyone is idle by now
    assert first.tracker.users == []
    assert first.counters.users_evicted == users
    with make_session_factory(engine)() as s:  # their visits closed where they were last seen
        assert repo.open_visits(s, "hq") == []
        left = {v.user_id: v.left_ms for v in repo.zone_visits(s, "hq", "all", 0, 2**62, 100)}
    assert left == latest
    result = first.process(groups[8])
    exits = [m for m in result.messages if isinstance(m, ZoneMessage)]
    assert {(m.user_id, m.kind, m.t_ms, m.probability) for m in exits} == {
        (u, "exit", t, 0.0) for u, t in latest.items()
    }
    receipts = result.receipts
    assert all(getattr(r, "status", None) == "applied" for r in receipts)
    assert not any(getattr(r, "tracking", True) for r in receipts)  # back without a fix: not tracked
    restarted = session()  # the snapshot has no users, the log only the batch after it
    assert set(restarted.tracker.users) == {s.header.effective_user_id for s in groups[8]}
    assert not any(restarted.tracker.is_tracking(u) for u in restarted.tracker.users)
    engine.dispose()


def test_a_building_without_floor_0_comes_back_with_a_user_who_started_at_a_lift_on_floor_2(
    database_url: str,
) -> None:
    """The batch log is replayed as the live path converted it: an anchor reading of a lift pinned on floor 2
    places the phone on floor 2 again, in a building whose floors are 1 and 2 (a replay that took every
    known anchor on floor 0 refused the log, and the building never loaded again)."""
    from schemas.anchors import AnchorType
    from server.store.models import FloorRow

    engine = make_engine(database_url)
    upgrade(engine)
    with make_session_factory(engine).begin() as s:
        s.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
        s.add_all([FloorRow(building_id="hq", level=lv, name=f"F{lv}") for lv in (1, 2)])
    building = _building(engine)
    building.anchor_edits.put_known(
        "lift", KnownAnchorIn(type=AnchorType.ELEVATOR, position=Position(x_m=10.0, y_m=5.0), floor=2)
    )
    t0 = 1_767_225_600_000
    batches = []
    for seq in range(6):
        steps = [{"t_ms": t0 + seq * 1000 + 500, "length_m": 0.7, "azimuth_rad": 0.3}]
        landmarks = [{"kind": "anchor", "t_ms": t0, "anchor_id": "lift"}] if seq == 0 else []
        batch = SensorBatch.model_validate(
            {
                "building_id": "hq",
                "device_id": "phone",
                "batch_id": f"b{seq}",
                "seq": seq,
                "steps": steps,
                "landmarks": landmarks,
            }
        )
        batches.append(Submission.of(batch, batch.model_dump_json().encode(), 0))
    for sub in batches:
        (receipt,) = building.process([sub]).receipts
        assert getattr(receipt, "status", None) == "applied", receipt
    assert building.tracker.floor_of("phone")[0] == 2
    at_crash = _estimates(building)
    del building  # as after kill -9: the log holds every batch

    restarted = _building(engine)
    assert restarted.counters.replayed == len(batches)
    assert restarted.tracker.floor_of("phone")[0] == 2
    assert _estimates(restarted) == at_crash
    receipts = [restarted.process([sub]).receipts[0] for sub in batches]
    assert [getattr(r, "status", None) for r in receipts] == ["duplicate"] * len(batches)
    engine.dispose()


def _radio_map(folder: Path, job_id: str, subs: list[Submission]) -> None:
    """A finished build's record and radio map: the scans of these batches, placed on a line across the
    floor (where exactly does not matter here: only that the filters use them)."""
    from datetime import UTC, datetime

    from schemas.signal_maps import SignalMapJob, SignalMapStatus
    from server.ingestion.radio_maps import RECORD, write_radio_map

    scans = [s for sub in subs for s in SensorBatch.model_validate_json(sub.raw).wifi_scans]
    assert scans
    done = folder / "hq" / job_id
    done.mkdir(parents=True, exist_ok=True)
    xy = np.column_stack([np.linspace(5.0, 55.0, len(scans)), np.full(len(scans), 25.0)])
    aps = [{ap.bssid: ap.rssi_dbm for ap in s.aps} for s in scans]
    write_radio_map(done, xy, aps, np.array([s.t_ms for s in scans]), np.zeros(len(scans), dtype=np.int64))
    now = datetime.now(UTC)
    job = SignalMapJob(
        id=job_id,
        building_id="hq",
        status=SignalMapStatus.DONE,
        created_at=now,
        finished_at=now,
        recordings=1,
    )
    (done / RECORD).write_text(job.model_dump_json())


@pytest.mark.parametrize("change", ["floor plan", "radio map"])
def test_a_change_between_batches_survives_a_crash_exactly(
    sqlite_url: str, tmp_path: Path, change: str
) -> None:
    """A floor plan uploaded, or a build's radio map loaded, between two batches: after a crash the log's
    batches from before it are replayed without it and those after it with it, as they were applied (each
    change is written with a snapshot), and a build that finished while the server was down joins after
    the replay."""
    from schemas.floor_plans import FLOOR_PLAN_EXAMPLE, FloorPlan

    groups = _groups(CROWD)[:14]

    def building(engine: Engine, maps: Path) -> BuildingHost:
        config = TrackingConfig(
            tracker_params(SETTINGS), load_calibration(None), SETTINGS.seed, math.inf, Retention(), maps
        )
        return BuildingHost("hq", make_session_factory(engine), config)

    def changed(b: BuildingHost, maps: Path) -> None:
        if change == "floor plan":
            b.floor_plans.put(0, FloorPlan.model_validate(FLOOR_PLAN_EXAMPLE))
        else:
            _radio_map(maps, "build1", [s for g in groups[:5] for s in g])
            loaded = b.load_radio_map()
            assert loaded is not None
            assert loaded[0] == "build1"
            assert loaded[1] > 0

    def floors(url: str) -> Engine:
        engine = _fresh_building(url)
        from server.store.models import FloorRow

        with make_session_factory(engine).begin() as s:
            s.add(FloorRow(building_id="hq", level=0, name="G", width_m=60.0, height_m=50.0))
        return engine

    reference = building(floors(sqlite_url.replace(".sqlite3", "-ref.sqlite3")), tmp_path / "reference")
    for group in groups[:6]:
        reference.process(group)
    changed(reference, tmp_path / "reference")
    for group in groups[6:10]:
        reference.process(group)
    at_crash = _estimates(reference)

    maps = tmp_path / "signal_maps"
    engine = floors(sqlite_url)
    crashed = building(engine, maps)
    for group in groups[:6]:
        crashed.process(group)
    changed(crashed, maps)
    for group in groups[6:10]:
        crashed.process(group)
    assert _estimates(crashed) == at_crash
    del crashed  # as after kill -9

    restarted = building(engine, maps)
    assert restarted.counters.replayed == sum(len(g) for g in groups[6:10])
    assert _estimates(restarted) == at_crash
    for group in groups[10:]:
        reference.process(group)
        restarted.process(group)
    assert _estimates(restarted) == _estimates(reference)
    if change == "radio map":  # a build finished while the server was down: it joins after the replay
        del restarted
        _radio_map(maps, "build2", [s for g in groups[5:9] for s in g])
        again = building(engine, maps)
        assert again.tracker.radio_map_id == "build2"
        assert _estimates(again) == _estimates(reference)  # the replay did not see it
    engine.dispose()


def test_the_position_history_after_a_crash_is_the_one_without(sqlite_url: str) -> None:
    """The history keeps one estimate a period of the phone's time: which one is decided the same way after a
    crash (the sampling's memory is in the snapshot, and the replay goes through it again)."""
    from server.store.models import PositionSnapshotRow

    groups = _groups(CROWD)[:16]
    retention = Retention(position_history_period_s=3.0)

    def history(engine: Engine) -> list[tuple[str, int]]:
        with make_session_factory(engine)() as s:
            rows = s.execute(select(PositionSnapshotRow.user_id, PositionSnapshotRow.t_ms)).all()
        return sorted((u, int(t)) for u, t in rows)

    reference_engine = _fresh_building(sqlite_url.replace(".sqlite3", "-ref.sqlite3"))
    reference = _building(reference_engine, retention=retention)
    engine = _fresh_building(sqlite_url)
    crashed = _building(engine, snapshot_period_s=0.0, retention=retention)
    for group in groups[:9]:
        reference.process(group)
        crashed.process(group)
    del crashed  # as after kill -9, between its periodic snapshots
    restarted = _building(engine, snapshot_period_s=0.0, retention=retention)
    for group in groups[9:]:
        reference.process(group)
        restarted.process(group)
    assert history(engine) == history(reference_engine)
    assert len(history(engine)) < reference.counters.estimates / 2
    engine.dispose()
    reference_engine.dispose()


def test_an_operators_retried_edit_changes_nothing(sqlite_url: str) -> None:
    """A PUT of an anchor or a floor plan sent again (its answer lost in a crash, say) finds it as asked and
    changes nothing: no tracker call, no snapshot, no live message; a PUT that moves it does."""
    from schemas.anchors import AnchorType
    from schemas.floor_plans import FLOOR_PLAN_EXAMPLE, FloorPlan
    from server.store.models import FloorRow

    engine = _fresh_building(sqlite_url)
    with make_session_factory(engine).begin() as s:
        s.add(FloorRow(building_id="hq", level=0, name="G", width_m=60.0, height_m=50.0))
    building = _building(engine)
    for group in _groups(CROWD)[:4]:
        building.process(group)
    body = KnownAnchorIn(type=AnchorType.DOOR, position=Position(x_m=12.0, y_m=8.0), label="kiosk")
    first, messages = building.anchor_edits.put_known("kiosk", body)
    assert messages
    snapshots = building.counters.snapshots
    state = tracker_snapshot_bytes(building)
    again, messages = building.anchor_edits.put_known("kiosk", body)
    assert (again, messages) == (first, [])
    assert building.counters.snapshots == snapshots
    assert tracker_snapshot_bytes(building) == state
    moved, messages = building.anchor_edits.put_known("kiosk", body.model_copy(update={"label": "kiosk 2"}))
    assert messages
    assert moved.label == "kiosk 2"
    plan = FloorPlan.model_validate(FLOOR_PLAN_EXAMPLE)
    building.floor_plans.put(0, plan)
    snapshots = building.counters.snapshots
    state = tracker_snapshot_bytes(building)
    building.floor_plans.put(0, plan)
    assert building.counters.snapshots == snapshots
    assert tracker_snapshot_bytes(building) == state
    engine.dispose()


def tracker_snapshot_bytes(building: BuildingHost) -> bytes:
    from server.buildings.snapshot import pickled

    return pickled(building.building.state())
