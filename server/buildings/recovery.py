"""A building's tracking state that survives a crash.

``RecoverableBuilding`` loads a building (its last snapshot plus the batches logged since, replayed in their
original engine calls; or, when there is no usable snapshot, the SQL anchor map), snapshots its tracker
periodically and when asked, and clears the logged batch bodies a snapshot covers. ``BuildingHost``
(``server.buildings.host``) builds the batch path and the operator's anchor edits on it.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import time

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from schemas.anchors import AnchorType
from schemas.floor_plans import FloorPlan
from schemas.sensors import SensorBatch
from server.buildings import snapshot as tracker_snapshot
from server.buildings.anchor_ids import AnchorIds
from server.buildings.config import TrackingConfig
from server.buildings.counters import Counters
from server.buildings.ledger import DeviceLedger
from server.buildings.submissions import BatchHeader
from server.errors import NotFoundError
from server.ingestion import convert
from server.ingestion.extent import Extent
from server.ingestion.floor_plans import engine_plan
from server.ingestion.radio_maps import latest_radio_map
from server.store import repositories as repo
from server.store.batches import LoggedBatch, clear_covered_bodies, logged_batches
from server.store.models import BuildingRow
from slam_core.encounters.models import Calibration
from slam_core.geo import GeoFrame
from slam_core.tracking.tracker import BuildingTracker, TrackerParams

logger = logging.getLogger(__name__)

TRACKED_LEVEL = 0
"""The floor users are tracked on (estimates say floor 0): its plan weighs their steps. Plans of other floors
are kept and served, and constrain no one until users are tracked across floors."""


class RecoverableBuilding:
    """Used from the building's single worker thread only, like ``BuildingHost``."""

    def __init__(self, building_id: str, sessions: sessionmaker[Session], config: TrackingConfig) -> None:
        self.building_id = building_id
        self.retention = config.retention
        self._last_heard: dict[str, float] = {}  # user -> wall time of its last applied batch
        self.snapshot_period_s = config.snapshot_period_s
        self.group_linger_s = config.group_linger_s
        self._sessions = sessions
        self.counters = Counters()
        self.restore_problem: str | None = None
        self._config = config
        self._last_snapshot = -math.inf
        self._log_to_clear = False  # a snapshot was written since the log's covered bodies were last cleared
        self._background = tracker_snapshot.BackgroundSnapshots(building_id)
        self._load()

    def _load(self, snapshot_always: bool = True) -> None:
        """The building as its SQL holds it: the last snapshot plus the batches logged since, replayed in
        their original engine calls (or, without a usable snapshot, the SQL anchor map). Then a snapshot
        covering the whole log, unless ``snapshot_always`` is off and the one in SQL was used: it still
        is the state before the log, which the log replays to the same filters."""
        params, calibration, seed = self._config.params, self._config.calibration, self._config.seed
        self.ids = AnchorIds()
        self._device_of_user: dict[str, str] = {}
        self._round = 0  # engine calls so far: the order a restart replays the batch log in
        with self._sessions() as session:
            building = repo.get_building(session, self.building_id)
            if building is None:
                raise NotFoundError(f"no building {self.building_id!r}")
            self.geo = building_geo(building)
            self.extent = Extent.of_floors(
                ((f.width_m, f.height_m) for f in repo.list_floors(session, self.building_id)),
                self._config.extent_margin_m,
            )
            self.devices = DeviceLedger(self.building_id, repo.devices(session, self.building_id))
            restored = self._restore(session, params, calibration)
            logged = logged_batches(session, self.building_id, after_round=self._round if restored else None)
            if not restored:
                # the filters start again, but the log still says which sequence numbers were applied; the
                # engine calls count on from the log's last, so the load snapshot covers the whole log
                for item in logged:
                    self.devices.replayed(BatchHeader.of(SensorBatch.model_validate_json(item.body)))
                self._round = max((item.applied_round for item in logged), default=self._round)
                logged = []
                self.tracker = BuildingTracker(params, calibration, seed=seed)
                for row in repo.list_anchors(session, self.building_id):
                    cov = np.array([[row.cov_xx, row.cov_xy], [row.cov_xy, row.cov_yy]])
                    index = self.tracker.restore_anchor(
                        np.array([row.x_m, row.y_m]),
                        cov,
                        convert.anchor_type_index(AnchorType(row.type)),
                        row.known,
                        row.observation_count,
                        row.last_seen_ms or 0,
                        row.signature.decode() if row.signature else "",
                    )
                    self.ids.link(index, row.public_id, row.label)
            plan = repo.floor_plan(session, self.building_id, TRACKED_LEVEL)
        # the plan is not in the snapshot: set before the log replays, as it was when the batches applied
        self.tracker.set_floor_plan(
            None if plan is None else engine_plan(FloorPlan.model_validate_json(plan))
        )
        self.load_radio_map()
        self._replay(logged)
        self.replayed = len(logged)
        """Batches the last load replayed from the batch log (none after a clean stop)."""
        if snapshot_always or not restored:
            self.snapshot(clear_log=True)  # it covers the whole log now

    def load_radio_map(self) -> int:
        """Load the radio map of the building's latest finished signal-map build into the tracker's
        fingerprints (once per build); returns the scans that joined. A map that cannot be read is logged
        and skipped: the building tracks without it."""
        root = self._config.signal_maps_dir
        if root is None:
            return 0
        try:
            radio = latest_radio_map(root, self.building_id, unless=self.tracker.radio_map_id)
        except ValueError as exc:
            logger.warning("building %s: radio map skipped: %s", self.building_id, exc)
            return 0
        if radio is None:
            return 0
        added = self.tracker.load_radio_map(radio.map_id, radio.xy, radio.bssids, radio.rss, radio.t_ms)
        logger.info(
            "building %s: %d scans of build %s joined its fingerprints", self.building_id, added, radio.map_id
        )
        return added

    def reload(self) -> None:
        """Throw the in-memory state away and load the building again from SQL, exactly as a restart does:
        what a rolled-back transaction had changed in the tracker is gone, what committed is all there."""
        self._background.discard()  # a snapshot taken from the state thrown away is never written
        self._load(snapshot_always=False)  # a reload pickles nothing: the snapshot in SQL is still right
        self.counters.reloads += 1

    def context(self) -> convert.BuildingContext:
        """What converting a batch needs of the building: its geo frame and its known anchors by id."""
        known = {}
        for public_id, index in self.ids.index.items():
            if self.tracker.crowd.is_live(index):
                mean, _, _, is_known, _, _ = self.tracker.crowd.anchor(index)
                if is_known:
                    known[public_id] = (float(mean[0]), float(mean[1]))
        return convert.BuildingContext(self.building_id, self.geo, known, extent=self.extent)

    def _restore(self, session: Session, params: TrackerParams, calibration: Calibration) -> bool:
        """Load the building's snapshot; False when there is none or it cannot be used."""
        row = repo.load_tracker_snapshot(session, self.building_id)
        if row is None:
            return False
        try:
            state = tracker_snapshot.decode(row.state, row.format_version, params, calibration)
        except tracker_snapshot.SnapshotMismatchError as exc:
            self.restore_problem = str(exc)
            self.counters.restore_failures += 1
            return False
        self.tracker = state.tracker
        for index, public_id in state.public_ids.items():
            self.ids.link(index, public_id, state.labels.get(index))
        self._device_of_user = dict(state.device_of_user)
        self._round = state.applied_round
        return True

    def _replay(self, logged: list[LoggedBatch]) -> None:
        """Re-apply the batches acknowledged after the snapshot, in their original engine calls. Their
        positions and anchors are already in SQL; only the in-memory filters are rebuilt."""
        for applied_round, items in itertools.groupby(logged, key=lambda b: b.applied_round):
            # a logged batch was accepted: it is replayed even if the margin has narrowed since
            ctx = dataclasses.replace(self.context(), extent=None)
            batches = []
            for item in items:
                batch = SensorBatch.model_validate_json(item.body)
                self._device_of_user[batch.effective_user_id] = batch.device_id
                self.devices.replayed(BatchHeader.of(batch))
                batches.append(convert.to_user_batch(batch, ctx).user_batch)
            outcome = self.tracker.apply(batches)
            for index in outcome.anchors_changed:
                if self.tracker.crowd.is_live(index):
                    self.ids.public_id(index)
            self._round = applied_round
            self.counters.replayed += len(batches)

    def _evict_idle_users(self) -> None:
        """Forget the users not heard from for ``Retention.user_idle_s`` (called right before a snapshot)."""
        idle_s = self.retention.user_idle_s
        if idle_s is None:
            return
        now = time.time()
        idle = [u for u in self.tracker.users if now - self._last_heard.setdefault(u, now) > idle_s]
        if idle:
            self.tracker.remove_users(idle)
            for u in idle:
                del self._last_heard[u]
            self.counters.users_evicted += len(idle)

    def _save_snapshot(self, session: Session) -> list[dict[str, object]]:
        """Write the snapshot and the devices' last sequence numbers; returns the device rows written (the
        ledger counts them saved once the transaction commits). Idle users are forgotten first."""
        self._background.discard()  # superseded by this one
        rows = self._snapshot_start(session)
        self._write_snapshot(session, self._round, tracker_snapshot.encode(self.building_state()))
        return rows

    def _write_snapshot(self, session: Session, applied_round: int, blob: bytes) -> None:
        """Store a snapshot taken at engine call ``applied_round``; the log it covers is cleared from now."""
        repo.save_tracker_snapshot(
            session, self.building_id, tracker_snapshot.FORMAT_VERSION, applied_round, blob
        )
        self._log_to_clear = True
        self.counters.snapshots += 1

    def _snapshot_start(self, session: Session) -> list[dict[str, object]]:
        self._evict_idle_users()
        rows = self.devices.unsaved_rows()
        repo.upsert_devices(session, rows)
        self._last_snapshot = time.monotonic()
        return rows

    def building_state(self) -> tracker_snapshot.BuildingState:
        """What a snapshot holds: the tracker and the building's bookkeeping, as of the last engine call."""
        return tracker_snapshot.BuildingState(
            self.tracker,
            dict(self.ids.public),
            dict(self.ids.labels),
            dict(self._device_of_user),
            self._round,
        )

    def _periodic_snapshot(self, session: Session) -> list[dict[str, object]]:
        """In a group's transaction: write the snapshot compressed since an earlier group, or take one when
        due (``tracker_snapshot.BackgroundSnapshots``). Returns the device rows written."""
        try:
            ready = self._background.ready()
        except Exception:
            logger.exception("building %s: compressing a snapshot failed", self.building_id)
            self.counters.snapshot_failures += 1
            ready = None
        if ready is not None:
            self._write_snapshot(session, *ready)
            return []
        if self._background.pending or time.monotonic() - self._last_snapshot < self.snapshot_period_s:
            return []
        rows = self._snapshot_start(session)
        self._background.take(self.building_state())
        return rows

    def _clear_log(self, session: Session, limit: int | None) -> None:
        """Clear the logged bodies the snapshot in SQL covers: all (``None``), or at most ``limit`` (a group
        clears a chunk, ``Retention.log_clear_per_batch`` per batch). Should the transaction roll back, what
        it cleared is cleared again after the next snapshot; a restart replays only the batches after the
        snapshot's round, so covered bodies left a while are never applied twice."""
        if not self._log_to_clear:
            return
        cleared = clear_covered_bodies(session, self.building_id, limit=limit)
        self.counters.log_bodies_cleared += cleared
        self._log_to_clear = cleared == limit

    def close(self) -> None:
        """Snapshot now and stop the snapshot thread (a clean stop leaves nothing to replay)."""
        self.snapshot(clear_log=True)
        self._background.close()

    def abandon(self) -> None:
        """Stop without writing anything: the building is another worker's now (its lease was lost)."""
        self._background.close()  # drops the pending snapshot unwritten

    def snapshot(self, clear_log: bool = False) -> None:
        """Snapshot now (on load, after operator edits, at shutdown); with ``clear_log`` the bodies it
        covers are cleared in the same transaction, else a chunk per group from the next group on."""
        with self._sessions.begin() as session:
            rows = self._save_snapshot(session)
            if clear_log:
                self._clear_log(session, None)
        self.devices.saved(rows)


def building_geo(building: BuildingRow) -> GeoFrame | None:
    """The building's geo-reference, if it has one."""
    if building.origin_lat_deg is None or building.origin_lon_deg is None:
        return None
    return GeoFrame(building.origin_lat_deg, building.origin_lon_deg, building.rotation_rad)
