"""One owner per building: its tracker, its anchor map in SQL, and the batch path of GUIDE.md.

``BuildingSession`` is synchronous and used only from its building's single worker thread, so a building's
batches and anchor edits are applied one group at a time, in arrival order. Batches that arrive while a
group is being processed form the next group: under load, one engine call and one transaction serve many
phones.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from datetime import UTC, datetime
from typing import Literal

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from schemas.anchors import AnchorType, BuildingAnchor, KnownAnchorIn
from schemas.api import BatchReceipt
from schemas.estimates import EncounterEvent, Estimate, EstimateSource
from schemas.live import AnchorMessage, EncounterMessage, LiveMessage, PositionMessage
from schemas.sensors import SensorBatch
from server import convert, tracker_snapshot
from server.device_ledger import DeviceLedger
from server.errors import ConflictError, InvalidInputError, NotFoundError, ProblemError
from server.recording import BuildingRecorder
from server.session_rows import anchor_row, position_row
from server.session_types import Counters, GroupResult, Retention, Submission
from server.store import repositories as repo
from server.store.batches import (
    AcceptedBatch,
    LoggedBatch,
    clear_covered_bodies,
    insert_batches_once,
    logged_batches,
)
from slam_core.encounters import Calibration
from slam_core.geo import GeoFrame
from slam_core.tracker import BuildingTracker, EstimateRow, TrackerParams, UserBatch

logger = logging.getLogger(__name__)


class BuildingSession:
    def __init__(
        self,
        building_id: str,
        sessions: sessionmaker[Session],
        params: TrackerParams,
        calibration: Calibration,
        seed: int,
        recorder: BuildingRecorder | None = None,
        snapshot_period_s: float = 60.0,
        retention: Retention | None = None,
    ) -> None:
        self.building_id = building_id
        self.retention = retention or Retention()
        self._last_prune = -math.inf
        self._last_heard: dict[str, float] = {}  # user -> wall time of its last applied batch
        self.recorder = recorder
        self.snapshot_period_s = snapshot_period_s
        self._sessions = sessions
        self.counters = Counters()
        self.restore_problem: str | None = None
        self._public: dict[int, str] = {}  # crowd index -> public id
        self._index: dict[str, int] = {}  # public id -> crowd index
        self._labels: dict[int, str | None] = {}
        self._device_of_user: dict[str, str] = {}
        self._next_anchor = 0
        self._round = 0  # engine calls so far: the order a restart replays the batch log in
        self._last_snapshot = -math.inf
        self._log_to_clear = False  # a snapshot was written since the log's covered bodies were last cleared
        self._background = tracker_snapshot.BackgroundSnapshots(building_id)
        with sessions() as session:
            building = repo.get_building(session, building_id)
            if building is None:
                raise NotFoundError(f"no building {building_id!r}")
            self.geo = (
                GeoFrame(building.origin_lat_deg, building.origin_lon_deg, building.rotation_rad)
                if building.origin_lat_deg is not None and building.origin_lon_deg is not None
                else None
            )
            self.devices = DeviceLedger(building_id, repo.devices(session, building_id))
            restored = self._restore(session, params, calibration)
            logged = logged_batches(session, building_id, after_round=self._round if restored else None)
            if not restored:
                # the filters start again, but the log still says which sequence numbers were applied; the
                # engine calls count on from the log's last, so the load snapshot covers the whole log
                for item in logged:
                    self.devices.replayed(SensorBatch.model_validate_json(item.body))
                self._round = max((item.applied_round for item in logged), default=self._round)
                logged = []
                self.tracker = BuildingTracker(params, calibration, seed=seed)
                for row in repo.list_anchors(session, building_id):
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
                    self._link(index, row.public_id, row.label)
        self._replay(logged)
        self.snapshot(clear_log=True)  # it covers the whole log now

    # ------------------------------------------------------------------ crash recovery
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
            self._link(index, public_id, state.labels.get(index))
        self._device_of_user = dict(state.device_of_user)
        self._round = state.applied_round
        return True

    def _replay(self, logged: list[LoggedBatch]) -> None:
        """Re-apply the batches acknowledged after the snapshot, in their original engine calls. Their
        positions and anchors are already in SQL; only the in-memory filters are rebuilt."""
        for applied_round, items in itertools.groupby(logged, key=lambda b: b.applied_round):
            ctx = self.context()
            batches = []
            for item in items:
                batch = SensorBatch.model_validate_json(item.body)
                self._device_of_user[batch.effective_user_id] = batch.device_id
                self.devices.replayed(batch)
                batches.append(convert.to_user_batch(batch, ctx).user_batch)
            outcome = self.tracker.apply(batches)
            for index in outcome.anchors_changed:
                if self.tracker.crowd.is_live(index):
                    self._public_id(index)
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
        repo.save_tracker_snapshot(
            session,
            self.building_id,
            tracker_snapshot.FORMAT_VERSION,
            self._round,
            tracker_snapshot.encode(self._session_state()),
        )
        self._log_to_clear = True
        self.counters.snapshots += 1
        return rows

    def _snapshot_start(self, session: Session) -> list[dict[str, object]]:
        self._evict_idle_users()
        rows = self.devices.unsaved_rows()
        repo.upsert_devices(session, rows)
        self._last_snapshot = time.monotonic()
        return rows

    def _session_state(self) -> tracker_snapshot.SessionState:
        return tracker_snapshot.SessionState(
            self.tracker, dict(self._public), dict(self._labels), dict(self._device_of_user), self._round
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
            applied_round, blob = ready
            repo.save_tracker_snapshot(
                session, self.building_id, tracker_snapshot.FORMAT_VERSION, applied_round, blob
            )
            self._log_to_clear = True
            self.counters.snapshots += 1
            return []
        if self._background.pending or time.monotonic() - self._last_snapshot < self.snapshot_period_s:
            return []
        rows = self._snapshot_start(session)
        self._background.take(self._session_state())
        return rows

    def _clear_log(self, session: Session, group_size: int) -> None:
        """In a group's transaction: clear a chunk of the logged bodies the snapshot in SQL covers
        (``Retention.log_clear_per_batch``). Should the transaction roll back, what it cleared is cleared
        again after the next snapshot; a restart replays only the batches after the snapshot's round, so
        covered bodies left a while are never applied twice."""
        if not self._log_to_clear:
            return
        chunk = max(1, int(self.retention.log_clear_per_batch * group_size))
        cleared = clear_covered_bodies(session, self.building_id, limit=chunk)
        self.counters.log_bodies_cleared += cleared
        self._log_to_clear = cleared == chunk

    def close(self) -> None:
        """Snapshot now and stop the snapshot thread (a clean stop leaves nothing to replay)."""
        self.snapshot(clear_log=True)
        self._background.close()

    def snapshot(self, clear_log: bool = False) -> None:
        """Snapshot now (on load, after operator edits, at shutdown); with ``clear_log`` the bodies it
        covers are cleared in the same transaction, else a chunk per group from the next group on."""
        with self._sessions.begin() as session:
            rows = self._save_snapshot(session)
            if clear_log:
                self.counters.log_bodies_cleared += clear_covered_bodies(session, self.building_id)
                self._log_to_clear = False
        self.devices.saved(rows)

    # ------------------------------------------------------------------ anchors
    def _link(self, index: int, public_id: str, label: str | None) -> None:
        self._public[index] = public_id
        self._index[public_id] = index
        self._labels[index] = label
        if public_id.startswith("a-") and public_id[2:].isdigit():
            self._next_anchor = max(self._next_anchor, int(public_id[2:]) + 1)

    def _public_id(self, index: int) -> str:
        if index not in self._public:
            while f"a-{self._next_anchor}" in self._index:
                self._next_anchor += 1
            self._link(index, f"a-{self._next_anchor}", None)
        return self._public[index]

    def context(self) -> convert.BuildingContext:
        known = {}
        for public_id, index in self._index.items():
            if self.tracker.crowd.is_live(index):
                mean, _, _, is_known, _, _ = self.tracker.crowd.anchor(index)
                if is_known:
                    known[public_id] = (float(mean[0]), float(mean[1]))
        return convert.BuildingContext(self.building_id, self.geo, known)

    def anchor(self, index: int) -> BuildingAnchor:
        mean, cov, type_index, known, count, last = self.tracker.crowd.anchor(index)
        return convert.building_anchor(
            self._public_id(index),
            self.building_id,
            mean,
            cov,
            type_index,
            known,
            count,
            int(last) if math.isfinite(last) and last > 0 else None,
            self._labels.get(index),
            signature=self.tracker.crowd.signature(index) or None,
        )

    def anchors(self) -> list[BuildingAnchor]:
        return [self.anchor(i) for i in sorted(self._public) if self.tracker.crowd.is_live(i)]

    def get_anchor(self, public_id: str) -> BuildingAnchor:
        index = self._index.get(public_id)
        if index is None or not self.tracker.crowd.is_live(index):
            raise NotFoundError(f"no anchor {public_id!r} in building {self.building_id!r}")
        return self.anchor(index)

    def put_known_anchor(
        self, public_id: str, body: KnownAnchorIn
    ) -> tuple[BuildingAnchor, list[LiveMessage]]:
        index = self._index.get(public_id)
        if index is not None and not self.tracker.crowd.is_live(index):
            raise ConflictError(f"anchor {public_id!r} was deleted or merged; pick a new id")
        xy = np.array([body.position.x_m, body.position.y_m])
        type_index = convert.anchor_type_index(body.type)
        index = self.tracker.pin_anchor(xy, type_index, index)
        self._link(index, public_id, body.label)
        anchor = self.anchor(index)
        with self._sessions.begin() as session:
            repo.save_anchor(session, anchor_row(self.building_id, anchor))
            rows = self._save_snapshot(session)
        self.devices.saved(rows)
        return anchor, [AnchorMessage(anchor=anchor)]

    def delete_anchor(self, public_id: str) -> list[LiveMessage]:
        anchor = self.get_anchor(public_id)
        self.tracker.remove_anchor(self._index[public_id])
        with self._sessions.begin() as session:
            repo.delete_anchor(session, self.building_id, public_id)
            rows = self._save_snapshot(session)
        self.devices.saved(rows)
        return [AnchorMessage(anchor=anchor, deleted=True)]

    def merge_anchors(self, public_ids: list[str]) -> tuple[BuildingAnchor, list[LiveMessage]]:
        if len(set(public_ids)) != len(public_ids):
            raise InvalidInputError("anchor_ids must be distinct")
        olds = [self.get_anchor(p) for p in public_ids]
        keep = self._index[public_ids[0]]
        for p in public_ids[1:]:
            self.tracker.merge_anchors(keep, self._index[p])
        merged = self.anchor(keep)
        with self._sessions.begin() as session:
            repo.save_anchor(session, anchor_row(self.building_id, merged))
            for p in public_ids[1:]:
                repo.delete_anchor(session, self.building_id, p)
            rows = self._save_snapshot(session)
        self.devices.saved(rows)
        messages: list[LiveMessage] = [AnchorMessage(anchor=merged)]
        messages += [AnchorMessage(anchor=a, deleted=True) for a in olds[1:]]
        return merged, messages

    # ------------------------------------------------------------------ batches
    def latest_estimate(self, user: str) -> Estimate | None:
        row = self.tracker.estimate(user)
        if row is None:
            return None
        return self._estimate(user, row)

    def _estimate(self, user: str, row: EstimateRow) -> Estimate:
        source = (
            EstimateSource.DYNAMICSLAM
            if self.tracker.params.filter.use_human_anchors
            else EstimateSource.SEMANTICSLAM
        )
        return convert.estimate(
            row, self.building_id, user, self._device_of_user.get(user, user), self.geo, source
        )

    def process(self, group: list[Submission]) -> GroupResult:
        """Apply a group of batches: dedupe, order, convert, track, persist, in one transaction."""
        ctx = self.context()
        results: list[BatchReceipt | ProblemError | None] = [None] * len(group)
        converted: dict[int, tuple[UserBatch, list[str]]] = {}
        for i, sub in enumerate(group):
            try:
                c = convert.to_user_batch(sub.batch, ctx)
            except ValueError as exc:
                results[i] = InvalidInputError(str(exc))
                continue
            converted[i] = (c.user_batch, c.warnings)
        messages: list[LiveMessage] = []
        order = list(converted)
        # late or applied, and by which engine call, is decided before anything is written: each row goes
        # in with the call that applies it (a retry is recognised by the insert itself, and was late anyway)
        calls = dict(zip(order, self.devices.plan([group[i].batch for i in order]), strict=True))
        base = self._round
        device_rows: list[dict[str, object]] = []
        with self._sessions.begin() as session:
            inserted = insert_batches_once(session, [self._accepted(group[i], calls[i], base) for i in order])
            by_call: dict[int, list[int]] = {}
            for i, row_id in zip(order, inserted, strict=True):
                b = group[i].batch
                if row_id is None:
                    self.counters.duplicates += 1
                    results[i] = self._receipt(b, "duplicate", converted[i][1])
                    continue
                if self.recorder is not None:
                    self.recorder.record_batch(group[i].raw, group[i].received_ns)
                call = calls[i]
                if call is None:
                    self.counters.late += 1
                    results[i] = self._receipt(b, "late", converted[i][1])
                    continue
                self._device_of_user[b.effective_user_id] = b.device_id
                row = self.devices.applied(b)
                if row is not None:
                    device_rows.append(row)
                by_call.setdefault(call, []).append(i)
            repo.upsert_devices(session, device_rows)
            # a user may have several batches in one group: one per user per engine call
            for call in sorted(by_call):
                now = by_call[call]
                self._round = base + call
                self._apply(session, group, converted, now, results, messages)
            device_rows += self._periodic_snapshot(session)
            self._clear_log(session, len(group))
            if time.monotonic() - self._last_prune >= self.retention.prune_period_s:
                self._prune(session)
        self.devices.saved(device_rows)
        if self.recorder is not None:
            self.recorder.flush()
        self.counters.batches += len(group)
        return GroupResult([r if r is not None else ProblemError("not processed") for r in results], messages)

    def _apply(
        self,
        session: Session,
        group: list[Submission],
        converted: dict[int, tuple[UserBatch, list[str]]],
        now: list[int],
        results: list[BatchReceipt | ProblemError | None],
        messages: list[LiveMessage],
    ) -> None:
        """One engine call over these batches (at most one per user); their receipts, positions, anchor
        changes and live messages."""
        outcome = self.tracker.apply([converted[i][0] for i in now])
        heard = time.time()
        for i in now:
            self._last_heard[converted[i][0].user] = heard
        encounters = [convert.encounter_event(e, self.building_id) for e in outcome.encounters]
        self.counters.encounters += len(encounters)
        self.counters.encounters_applied += sum(e.applied for e in encounters)
        self.counters.encounter_detections += outcome.detections
        estimates = {u: self._estimate(u, row) for u, row in outcome.estimates.items()}
        self.counters.estimates += len(estimates)
        if self.recorder is not None:
            self.recorder.record_estimates(list(estimates.values()), group[now[0]].received_ns)
        stored_at_ms = int(heard * 1000)
        rows = [position_row(self.building_id, e, stored_at_ms) for e in estimates.values()]
        repo.add_positions(session, rows)
        for index in outcome.anchors_changed:
            if self.tracker.crowd.is_live(index):
                anchor = self.anchor(index)
                repo.save_anchor(session, anchor_row(self.building_id, anchor))
                messages.append(AnchorMessage(anchor=anchor))
        messages += [PositionMessage(estimate=e) for e in estimates.values()]
        messages += [EncounterMessage(encounter=e) for e in encounters]
        by_user: dict[str, list[EncounterEvent]] = {}
        for e in encounters:
            by_user.setdefault(e.user_a, []).append(e)
            if e.user_b != e.user_a:
                by_user.setdefault(e.user_b, []).append(e)
        for i in now:
            b = group[i].batch
            report = outcome.reports[converted[i][0].user]
            self.counters.steps_dropped += report.steps_dropped
            self.counters.steps_detected += report.steps_detected
            self.counters.imu_samples_dropped += report.imu_samples_dropped
            self.counters.recentred += report.recentred
            self.counters.fingerprint_fixes += report.fingerprint_fixes
            warnings = list(converted[i][1])
            if report.imu_samples_dropped:
                warnings.append(
                    f"{report.imu_samples_dropped} IMU samples skipped: not newer than the samples "
                    "already dead-reckoned for this user"
                )
            if report.steps_dropped:
                warnings.append(_dropped_warning(report.steps_dropped, report.status))
            results[i] = self._receipt(
                b, "applied", warnings, estimates.get(b.effective_user_id), by_user.get(b.effective_user_id)
            )

    def _prune(self, session: Session) -> None:
        """Delete a chunk of position history and of batch ids past their retention."""
        r = self.retention
        now = time.time()
        positions_before = (
            None if r.position_history_days is None else int((now - r.position_history_days * 86_400) * 1e3)
        )
        batches_before = (
            None if r.batch_ids_days is None else datetime.fromtimestamp(now - r.batch_ids_days * 86_400, UTC)
        )
        positions, batches = repo.prune_history(
            session, self.building_id, positions_before, batches_before, r.prune_chunk
        )
        self.counters.pruned_positions += positions
        self.counters.pruned_batches += batches
        self._last_prune = time.monotonic()

    def _accepted(self, sub: Submission, call: int | None, base: int) -> AcceptedBatch:
        span = sub.batch.time_span_ms()
        return AcceptedBatch(
            self.building_id,
            sub.batch.device_id,
            sub.batch.batch_id,
            sub.batch.seq,
            None if span is None else span[0],
            None if span is None else span[1],
            len(sub.raw),
            None if call is None else sub.raw,  # a late batch is never replayed: nothing to log
            None if call is None else base + call,
        )

    def _receipt(
        self,
        batch: SensorBatch,
        status: Literal["applied", "duplicate", "late"],
        warnings: list[str],
        estimate: Estimate | None = None,
        encounters: list[EncounterEvent] | None = None,
    ) -> BatchReceipt:
        user = batch.effective_user_id
        if estimate is None:
            estimate = self.latest_estimate(user)
        return BatchReceipt(
            batch_id=batch.batch_id,
            status=status,
            duplicate=status == "duplicate",
            tracking=self.tracker.is_tracking(user),
            estimate=estimate,
            encounters=encounters or [],
            warnings=warnings,
        )


def _dropped_warning(n: int, status: str) -> str:
    if status != "tracking":
        return (
            f"{n} steps skipped: the user has no position yet (send a fix, a tag or a known-anchor reading)"
        )
    return f"{n} steps skipped: out of time order, or turns without any azimuth to start from"
