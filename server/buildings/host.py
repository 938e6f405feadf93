"""One owner per building: its tracker, its anchor map in SQL, and the path of one batch (docs/architecture).

``BuildingHost`` is synchronous and used only from its building's one thread, so a building's batches and
its operators' edits are applied one at a time, in arrival order. Batches that arrive while a group is being
processed form the next group: under load, one tracker call and one transaction serve many phones.

The host owns the building as loaded (``server.buildings.building.Building``), the ``Recovery`` that loads
it and writes its snapshots, and its parts, each one concern: the batch path (``batch_path``), anchor edits
(``anchor_edits``), floor plans (``floor_plans``), zones (``zones``), users (``users``), and the recording
and retention (``upkeep``). A part changes the building only in a transaction of its own; a part that must
write a snapshot with its change asks the host (``save_snapshot``), which alone decides what goes before one.
"""

from __future__ import annotations

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from server.buildings.anchor_edits import AnchorEdits
from server.buildings.batch_path import BatchPath
from server.buildings.building import Building
from server.buildings.config import Retention, TrackingConfig
from server.buildings.counters import Counters
from server.buildings.floor_plans import FloorPlans
from server.buildings.recovery import Recovery, load_radio_map
from server.buildings.submissions import GroupResult, Submission
from server.buildings.upkeep import Upkeep
from server.buildings.users import Users
from server.buildings.zones import Zones
from server.recordings.recorder import BuildingRecorder
from server.settings import Settings
from server.slam.config import load_calibration, tracker_params
from server.store import repositories as repo
from server.store.db import is_disk_full, make_engine, make_session_factory
from server.store.wal_checkpoints import checkpoint_in_background
from server.store.writer_turns import writer_turns
from slam_core.geo import GeoFrame
from slam_core.tracking.tracker import BuildingTracker

IDLE_S = 5.0
"""A building that has had no batch for this long is told so (``BuildingHost.idle``)."""


class BuildingHost:
    """A building served from one thread: loaded from SQL by its ``Recovery`` at construction (its last
    snapshot and the batches logged since), then its parts. Used from the building's thread only."""

    def __init__(
        self,
        building_id: str,
        sessions: sessionmaker[Session],
        config: TrackingConfig,
        recorder: BuildingRecorder | None = None,
    ) -> None:
        counters = Counters()
        with sessions() as session:
            turns = writer_turns(session.get_bind().engine)
        self.building = Building(building_id, sessions, config, counters, recorder, turns)
        self.recovery = Recovery(building_id, sessions, config, counters)
        self.users = Users(self.building, self.save_snapshot, self.reload)
        self.upkeep = Upkeep(self.building)
        self.anchor_edits = AnchorEdits(self.building, self.save_snapshot, self.reload)
        self.floor_plans = FloorPlans(self.building, self.save_snapshot, self.reload)
        self.zones = Zones(self.building, self.save_snapshot, self.reload)
        self.batches = BatchPath(self.building, self.users, self.zones, self.upkeep, self, self.reload)
        self._load(start=True)

    # what the building's handle reads of it
    @property
    def building_id(self) -> str:
        return self.building.building_id

    @property
    def counters(self) -> Counters:
        return self.building.counters

    @property
    def recorder(self) -> BuildingRecorder | None:
        return self.building.recorder

    @property
    def group_linger_s(self) -> float:
        return self.building.config.group_linger_s

    @property
    def tracker(self) -> BuildingTracker:
        return self.building.tracker

    @property
    def geo(self) -> GeoFrame | None:
        return self.building.geo

    @property
    def restore_problem(self) -> str | None:
        """Why the building's last snapshot could not be used, if it could not."""
        return self.recovery.restore_problem

    def process(self, group: list[Submission]) -> GroupResult:
        """A group of batches through the batch path (``BatchPath.process``)."""
        return self.batches.process(group)

    def idle(self) -> None:
        """Called when no batch has come for ``IDLE_S``."""
        self.upkeep.idle()

    # ------------------------------------------------------------------ loading
    def _load(self, start: bool) -> None:
        """The building as its SQL holds it (``Recovery.load``). On a start, the batches replayed from the log
        recorded again, and a snapshot covering the whole log; on a reload (after a failed transaction,
        nothing lost from the recordings), a snapshot only if the one in SQL was not used or a radio map
        joined: else it still is the state before the log, which the log replays to the same filters."""
        loaded = self.recovery.load()
        self.building.adopt(loaded)
        if start:
            self.upkeep.record_again(loaded.replayed)
        if start or not loaded.restored or loaded.radio_map_loaded:
            self.snapshot(clear_log=True)  # it covers the whole log now

    def reload(self) -> None:
        """Throw the in-memory state away and load the building again from SQL, exactly as a restart does:
        what a rolled-back transaction had changed in the tracker is gone, what committed is all there."""
        self.recovery.discard()  # a snapshot taken from the state thrown away is never written
        try:
            self._load(start=False)  # a reload pickles nothing: the snapshot in SQL is still right
        except Exception as exc:
            if not is_disk_full(exc):
                raise
            # loaded, but its snapshot (of a building without a usable one) could not be written: the log
            # still holds every batch it would cover, and the next snapshot will
        self.counters.reloads += 1

    def load_radio_map(self) -> tuple[str, int] | None:
        """Load the radio map of the building's latest finished signal-map build into the tracker's
        fingerprints (once per build), and snapshot: a restart replays the batches after the load with its
        scans and none before it. Returns the build loaded and the scans that joined; None when there was
        none newer to load."""
        b = self.building
        before = b.tracker.radio_map_id
        added = load_radio_map(b.tracker, b.config.signal_maps_dir, b.building_id)
        loaded = b.tracker.radio_map_id
        if loaded is None or loaded == before:
            return None
        self.snapshot()
        return loaded, added

    # ------------------------------------------------------------------ snapshots
    def snapshot(self, clear_log: bool = False) -> None:
        """Snapshot now (on load, after a radio map, at shutdown); with ``clear_log`` the bodies it covers
        are cleared in the same transaction, else a chunk per group from the next group on."""
        with self.building.sessions.begin() as session:
            rows = self.save_snapshot(session)
            if clear_log:
                self.recovery.clear_log(session, None)
        self.building.devices.saved(rows)

    def save_snapshot(self, session: Session) -> list[dict[str, object]]:
        """Write the snapshot and the devices' last sequence numbers in the caller's transaction; returns the
        device rows written (the ledger counts them saved once the transaction commits). Before it: idle
        users forgotten, and the recording flushed (every batch a snapshot covers is in the recordings)."""
        rows = self._snapshot_start(session)
        self.upkeep.flush_recording()
        self.recovery.write(session, self.building.state())
        return rows

    def periodic(self, session: Session, group_size: int) -> list[dict[str, object]]:
        """In a group's transaction: write the snapshot compressed since an earlier group, or take one when
        due; then clear a chunk of the logged bodies a snapshot covers (``Retention.log_clear_per_batch`` a
        batch). Returns the device rows written."""
        rows: list[dict[str, object]] = []
        if self.recovery.ready:
            self.upkeep.flush_recording()
        if not self.recovery.write_ready(session) and self.recovery.due:
            rows = self._snapshot_start(session)
            self.recovery.take(self.building.state())
        per_batch = self.building.config.retention.log_clear_per_batch
        self.recovery.clear_log(session, max(1, int(per_batch * group_size)))
        return rows

    def _snapshot_start(self, session: Session) -> list[dict[str, object]]:
        """Before a snapshot: idle users forgotten (their zone visits closed), the devices' unsaved rows
        written."""
        self.building.told += self.zones.close_lost(session, self.users.evict_idle())
        rows = self.building.devices.unsaved_rows()
        repo.upsert_devices(session, rows)
        return rows

    # ------------------------------------------------------------------ stopping
    def close(self) -> None:
        """Snapshot now and stop the snapshot thread (a clean stop leaves nothing to replay)."""
        self.snapshot(clear_log=True)
        self.recovery.close()

    def abandon(self) -> None:
        """Stop without writing anything: another cluster worker holds the building now (its lease was
        lost)."""
        self.recovery.close()  # drops the pending snapshot unwritten


def tracking_config(settings: Settings) -> TrackingConfig:
    """How the settings have every building tracked."""
    retention = Retention(
        position_history_days=settings.position_history_days or None,
        position_history_period_s=settings.position_history_period_s,
        batch_ids_hours=settings.batch_ids_hours or None,
        recording_days=settings.recording_days or None,
        recording_max_bytes=int(settings.recording_max_gb * 1e9) or None,
        user_idle_s=settings.user_idle_s or None,
    )
    return TrackingConfig(
        tracker_params(settings),
        load_calibration(settings.encounter_calibration),
        settings.seed,
        settings.snapshot_period_s,
        retention,
        settings.data_dir / "signal_maps",
        settings.extent_margin_m,
        settings.group_linger_ms / 1000.0,
    )


def open_building(settings: Settings, building_id: str, engine: Engine | None = None) -> BuildingHost:
    """A building's tracking as the settings describe it, on its own database engine (a building's
    process; ``engine``: that engine, made by the caller, who disposes of it), its write-ahead log
    checkpointed beside the batch path; raises NotFoundError for an unknown building."""
    engine = engine or make_engine(settings.resolved_database_url)
    checkpoint_in_background(engine, settings.sqlite_checkpoint_period_s)  # stops when the process does
    sessions = make_session_factory(engine)
    recorder = BuildingRecorder(settings.recordings_dir, building_id) if settings.record else None
    return BuildingHost(building_id, sessions, tracking_config(settings), recorder)
