"""A building's tracking state that survives a crash.

``Recovery`` loads a building (its last snapshot plus the batches logged since, replayed in their original
tracker calls; or, when there is no usable snapshot, the SQL anchor map), writes its snapshots, periodically
and when asked, and clears the logged batch bodies a snapshot covers. The building's host
(``server.buildings.host.BuildingHost``) owns one and decides when.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

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
from server.buildings.rows import HistorySampling
from server.buildings.submissions import BatchHeader
from server.errors import NotFoundError
from server.ingestion import convert
from server.ingestion.extent import Extent
from server.ingestion.floor_plans import engine_plan
from server.ingestion.radio_maps import latest_radio_map
from server.ingestion.zones import set_tracker_zones
from server.store import repositories as repo
from server.store.batches import LoggedBatch, clear_covered_bodies, logged_batches
from server.store.models import BuildingRow, FloorRow
from slam_core.encounters.models import Calibration
from slam_core.geo import GeoFrame
from slam_core.tracking.tracker import BuildingTracker, TrackerParams

logger = logging.getLogger(__name__)


@dataclass
class Loaded:
    """A building as its SQL holds it, ready to take batches."""

    tracker: BuildingTracker
    ids: AnchorIds
    device_of_user: dict[str, str]
    tracker_call: int
    """Tracker calls so far: the order a restart replays the batch log in."""
    devices: DeviceLedger
    geo: GeoFrame | None
    extent: Extent | None
    replayed: list[bytes]
    """The bodies of the batches replayed from the batch log (none after a clean stop), to be recorded
    again: a crash may have cut them from the recordings."""
    restored: bool
    """From its snapshot; else from its SQL anchor map, the filters started anew."""
    history: HistorySampling
    """Which estimates join the position history: as the snapshot left it, advanced by the replay."""
    radio_map_loaded: bool = False
    """A newer radio map joined after the log was replayed (a build that finished while it was down)."""


class Recovery:
    """The part of a building that survives a crash, owned by its host (``server.buildings.host``): it loads
    the building, writes its snapshots (now, or compressed in the background between groups) and clears
    the logged batch bodies a snapshot covers. Used from the building's thread only."""

    def __init__(
        self, building_id: str, sessions: sessionmaker[Session], config: TrackingConfig, counters: Counters
    ) -> None:
        self.building_id = building_id
        self._sessions = sessions
        self._config = config
        self.counters = counters
        self.restore_problem: str | None = None
        self._last_snapshot = -math.inf
        self._log_to_clear = False  # a snapshot was written since the log's covered bodies were last cleared
        self._background = tracker_snapshot.BackgroundSnapshots(building_id)

    def load(self) -> Loaded:
        """The building as its SQL holds it: the last snapshot plus the batches logged since, replayed in
        their original tracker calls (or, without a usable snapshot, the SQL anchor map)."""
        params, calibration, seed = self._config.params, self._config.calibration, self._config.seed
        ids = AnchorIds()
        device_of_user: dict[str, str] = {}
        tracker_call = 0
        history = HistorySampling(self._config.retention.position_history_period_s)
        with self._sessions() as session:
            building = repo.get_building(session, self.building_id)
            if building is None:
                raise NotFoundError(f"no building {self.building_id!r}")
            geo = building_geo(building)
            floors = repo.list_floors(session, self.building_id)
            extent = Extent.of_floors(((f.width_m, f.height_m) for f in floors), self._config.extent_margin_m)
            devices = DeviceLedger(self.building_id, repo.devices(session, self.building_id))
            state = self._restore(session, params, calibration)
            if state is not None:
                tracker = state.tracker
                for index, public_id in state.public_ids.items():
                    ids.link(index, public_id, state.labels.get(index))
                device_of_user = dict(state.device_of_user)
                tracker_call = state.tracker_call
                history.latest_t_ms = dict(getattr(state, "history_t_ms", {}))
            logged = logged_batches(
                session, self.building_id, after_call=tracker_call if state is not None else None
            )
            if state is None:
                # the filters start again, but the log still says which sequence numbers were applied; the
                # tracker calls count on from the log's last, so the load snapshot covers the whole log
                for item in logged:
                    devices.replayed(BatchHeader.of(SensorBatch.model_validate_json(item.body)))
                tracker_call = max((item.tracker_call for item in logged), default=tracker_call)
                logged = []
                tracker = BuildingTracker(params, calibration, seed=seed)
                for row in repo.list_anchors(session, self.building_id):
                    cov = np.array([[row.cov_xx, row.cov_xy], [row.cov_xy, row.cov_yy]])
                    index = tracker.restore_anchor(
                        np.array([row.x_m, row.y_m]),
                        cov,
                        convert.anchor_type_index(AnchorType(row.type)),
                        row.known,
                        row.observation_count,
                        row.last_seen_ms or 0,
                        row.signature.decode() if row.signature else "",
                        row.floor,
                    )
                    ids.link(index, row.public_id, row.label)
            plans = {f.level: repo.floor_plan(session, self.building_id, f.level) for f in floors}
            zones = repo.list_zones(session, self.building_id)
        # floors and plans as SQL has them, set before the log replays: the snapshot holds them too (a plan
        # is uploaded with a snapshot), and a building started anew has them from here only
        tracker.set_levels(*building_levels(floors))
        for level, plan in plans.items():
            tracker.set_floor_plan(
                None if plan is None else engine_plan(FloorPlan.model_validate_json(plan)), level
            )
        # the zones too (who is inside comes with the snapshot; a tracker started anew has nobody inside, so
        # the visits SQL holds open are closed where their users were last seen)
        set_tracker_zones(tracker, zones)
        if state is None and zones:
            with self._sessions.begin() as session:
                repo.close_lost_visits(session, self.building_id)
        loaded = Loaded(
            tracker,
            ids,
            device_of_user,
            tracker_call,
            devices,
            geo,
            extent,
            [item.body for item in logged],
            state is not None,
            history,
        )
        self._replay(loaded, logged)
        # a radio map joins after the replay: the batches logged applied without it (its load writes a
        # snapshot), so a newer one is of a build that finished while the building was down
        before = tracker.radio_map_id
        load_radio_map(tracker, self._config.signal_maps_dir, self.building_id)
        loaded.radio_map_loaded = tracker.radio_map_id != before
        return loaded

    def _restore(
        self, session: Session, params: TrackerParams, calibration: Calibration
    ) -> tracker_snapshot.BuildingState | None:
        """The building's snapshot; None when there is none or it cannot be used."""
        row = repo.load_tracker_snapshot(session, self.building_id)
        if row is None:
            return None
        try:
            return tracker_snapshot.decode(row.state, row.format_version, params, calibration)
        except tracker_snapshot.SnapshotMismatchError as exc:
            self.restore_problem = str(exc)
            self.counters.restore_failures += 1
            return None

    def _replay(self, loaded: Loaded, logged: list[LoggedBatch]) -> None:
        """Re-apply the batches acknowledged after the snapshot, in their original tracker calls. Their
        positions and anchors are already in SQL; only the in-memory filters are rebuilt."""
        tracker = loaded.tracker
        for tracker_call, items in itertools.groupby(logged, key=lambda b: b.tracker_call):
            # converted as the live path converted it, but for the extent: a logged batch was accepted, and
            # is replayed even if the margin has narrowed since
            ctx = convert.building_context(self.building_id, tracker, loaded.ids.index, loaded.geo, None)
            batches = []
            for item in items:
                batch = SensorBatch.model_validate_json(item.body)
                loaded.device_of_user[batch.effective_user_id] = batch.device_id
                loaded.devices.replayed(BatchHeader.of(batch))
                batches.append(batch)
            try:
                outcome = tracker.apply([convert.to_user_batch(b, ctx).user_batch for b in batches])
            except Exception:
                # the live path applied these; a replay that cannot is the server's error. The building comes
                # back without them (an tracker call that raises changes nothing), counted and named in
                # /healthz, rather than not at all
                logger.exception(
                    "building %s: %d logged batches of tracker call %d could not be applied again",
                    self.building_id,
                    len(batches),
                    tracker_call,
                )
                self.counters.replay_failures += len(batches)
                self.counters.last_failure_unix_s = time.time()
            else:
                for index in outcome.anchors_changed:
                    if tracker.crowd.is_live(index):
                        loaded.ids.public_id(index)
                for user, row in outcome.estimates.items():  # their rows are in SQL: only the sampling moves
                    loaded.history.joins(user, row.t_ms)
                self.counters.replayed += len(batches)
            loaded.tracker_call = tracker_call

    # ------------------------------------------------------------------ snapshots
    def write(self, session: Session, state: tracker_snapshot.BuildingState) -> None:
        """Write a snapshot of ``state`` now, in the caller's transaction (a pending background one is
        superseded); the log it covers is cleared from now."""
        self._background.discard()
        self._last_snapshot = time.monotonic()
        self._store(session, state.tracker_call, tracker_snapshot.encode(state))

    def write_ready(self, session: Session) -> bool:
        """In a group's transaction: write the snapshot compressed in the background since an earlier
        group, if it is ready; whether one was written. A failure to compress is logged and counted."""
        try:
            ready = self._background.ready()
        except Exception:
            logger.exception("building %s: compressing a snapshot failed", self.building_id)
            self.counters.snapshot_failures += 1
            return False
        if ready is None:
            return False
        self._store(session, *ready)
        return True

    @property
    def ready(self) -> bool:
        """Whether a snapshot compressed in the background waits to be written (``write_ready``)."""
        return self._background.ready_to_write

    @property
    def due(self) -> bool:
        """Whether a periodic snapshot is due: none is being compressed, and ``snapshot_period_s`` passed."""
        return (
            not self._background.pending
            and time.monotonic() - self._last_snapshot >= self._config.snapshot_period_s
        )

    def take(self, state: tracker_snapshot.BuildingState) -> None:
        """Take a snapshot of ``state`` now and compress it in the background (``BackgroundSnapshots``); a
        later group's transaction writes it (``write_ready``)."""
        self._last_snapshot = time.monotonic()
        self._background.take(state)

    def _store(self, session: Session, tracker_call: int, blob: bytes) -> None:
        repo.save_tracker_snapshot(
            session, self.building_id, tracker_snapshot.FORMAT_VERSION, tracker_call, blob
        )
        self._log_to_clear = True
        self.counters.snapshots += 1

    def clear_log(self, session: Session, limit: int | None) -> None:
        """Clear the logged bodies the snapshot in SQL covers: all (``None``), or at most ``limit`` (a group
        clears a chunk, ``Retention.log_clear_per_batch`` per batch). Should the transaction roll back, what
        it cleared is cleared again after the next snapshot; a restart replays only the batches after the
        snapshot's round, so covered bodies left a while are never applied twice."""
        if not self._log_to_clear:
            return
        cleared = clear_covered_bodies(session, self.building_id, limit=limit)
        self.counters.log_bodies_cleared += cleared
        self._log_to_clear = cleared == limit

    def wait(self) -> None:
        """Block until the snapshot being compressed (if any) is, so that the next group writes it."""
        self._background.wait()

    def discard(self) -> None:
        """Forget the snapshot being compressed (taken from a state thrown away, it is never written)."""
        self._background.discard()

    def close(self) -> None:
        """Stop the compression thread; a snapshot still pending is dropped unwritten."""
        self._background.close()


def load_radio_map(tracker: BuildingTracker, signal_maps: Path | None, building_id: str) -> int:
    """Load the radio map of the building's latest finished signal-map build into the tracker's fingerprints
    (once per build); returns the scans that joined. A map that cannot be read is logged and skipped: the
    building tracks without it."""
    if signal_maps is None:
        return 0
    try:
        radio = latest_radio_map(signal_maps, building_id, unless=tracker.radio_map_id)
    except ValueError as exc:
        logger.warning("building %s: radio map skipped: %s", building_id, exc)
        return 0
    if radio is None:
        return 0
    on = np.flatnonzero(np.isin(radio.levels, tracker.levels))  # each scan joins its floor's fingerprints
    if on.size < len(radio):
        logger.warning(
            "building %s: %d scans of build %s skipped: on floors the building does not have",
            building_id,
            len(radio) - on.size,
            radio.map_id,
        )
    added = tracker.load_radio_map(
        radio.map_id,
        radio.xy[on],
        [radio.bssids[i] for i in on],
        [radio.rss[i] for i in on],
        radio.t_ms[on],
        radio.levels[on],
    )
    logger.info("building %s: %d scans of build %s joined its fingerprints", building_id, added, radio.map_id)
    return added


def building_levels(floors: list[FloorRow]) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """The building's floors and their elevations (NaN where the operator gave none); a building created
    without floors is one floor, level 0."""
    if not floors:
        return (0,), (math.nan,)
    return (
        tuple(f.level for f in floors),
        tuple(math.nan if f.elevation_m is None else f.elevation_m for f in floors),
    )


def building_geo(building: BuildingRow) -> GeoFrame | None:
    """The building's geo-reference, if it has one."""
    if building.origin_lat_deg is None or building.origin_lon_deg is None:
        return None
    return GeoFrame(building.origin_lat_deg, building.origin_lon_deg, building.rotation_rad)
