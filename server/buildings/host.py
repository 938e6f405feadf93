"""One owner per building: its tracker, its anchor map in SQL, and the path of one batch (docs/architecture).

``BuildingHost`` is synchronous and used only from its building's single worker thread, so a building's
batches and anchor edits are applied one group at a time, in arrival order. Batches that arrive while a
group is being processed form the next group: under load, one tracker call and one transaction serve many
phones.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Literal

import numpy as np
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from schemas.anchors import BuildingAnchor, KnownAnchorIn
from schemas.api import BatchReceipt
from schemas.estimates import EncounterEvent, Estimate, EstimateSource
from schemas.floor_plans import FloorPlan
from schemas.live import AnchorMessage, EncounterMessage, LiveMessage, PositionMessage, UserForgottenMessage
from server.buildings import snapshot as tracker_snapshot
from server.buildings.config import Retention, TrackingConfig
from server.buildings.counters import Counters
from server.buildings.recovery import Recovery, load_radio_map
from server.buildings.rows import anchor_row, position_row
from server.buildings.submissions import BatchHeader, GroupResult, Submission
from server.engine.config import load_calibration, tracker_params
from server.errors import (
    BatchFailedError,
    ConflictError,
    DiskFullError,
    ForbiddenError,
    InvalidInputError,
    NotFoundError,
    ProblemError,
)
from server.ingestion import convert, floor_plans
from server.recordings.recorder import BuildingRecorder, prune_recordings
from server.settings import Settings
from server.store import repositories as repo
from server.store.batches import (
    AcceptedBatch,
    insert_batches_once,
)
from server.store.db import is_disk_full, make_engine, make_session_factory, reclaim_free_pages
from server.store.wal_checkpoints import checkpoint_in_background
from server.store.writer_lock import writer_turns
from slam_core.tracking.tracker import EstimateRow, UserBatch

logger = logging.getLogger(__name__)

RECORDING_PRUNE_S = 60.0
"""How often a building deletes the recordings past their retention (a listing of every building's files)."""
IDLE_S = 5.0
"""A building that has had no batch for this long is told so (``BuildingHost.idle``)."""
RECLAIM_PAGES = 2048
"""At most this many free SQLite pages (8 MB of 4 KiB pages) handed back per prune."""


class BuildingHost:
    """A building's batch path and its operator's anchor edits, over its tracker; its ``Recovery`` loads it
    and writes its snapshots. Used from the building's single worker thread only."""

    def __init__(
        self,
        building_id: str,
        sessions: sessionmaker[Session],
        config: TrackingConfig,
        recorder: BuildingRecorder | None = None,
    ) -> None:
        self.building_id = building_id
        self.recorder = recorder
        self.retention = config.retention
        self.group_linger_s = config.group_linger_s
        self._sessions = sessions
        self.counters = Counters()
        self._config = config
        self._last_prune = -math.inf
        self._last_recording_prune = -math.inf
        self._last_heard: dict[str, float] = {}  # user -> wall time of its last applied batch
        self.recovery = Recovery(building_id, sessions, config, self.counters)
        self._load()
        with sessions() as session:
            self._writer_turns = writer_turns(session.get_bind().engine)

    # ------------------------------------------------------------------ loading and snapshots
    def _load(self, start: bool = True) -> None:
        """The building as its SQL holds it (``Recovery.load``). On a start, the batches replayed from the log
        recorded again, and a snapshot covering the whole log; on a reload (after a failed group, nothing
        lost from the recordings), a snapshot only if the one in SQL was not used or a radio map joined: else
        it still is the state before the log, which the log replays to the same filters."""
        loaded = self.recovery.load()
        self.tracker = loaded.tracker
        self.ids = loaded.ids
        self._device_of_user = loaded.device_of_user
        self._tracker_call = loaded.tracker_call
        self.devices = loaded.devices
        self.geo = loaded.geo
        self.extent = loaded.extent
        self.history = loaded.history
        if start:
            self._record_again(loaded.replayed)
        if start or not loaded.restored or loaded.radio_map_loaded:
            self.snapshot(clear_log=True)  # it covers the whole log now

    def _record_again(self, bodies: list[bytes]) -> None:
        """Record the batches the load replayed: a crash may have cut them from the recordings (those a
        snapshot covers are in them: they were flushed before it was written)."""
        if self.recorder is None or not bodies:
            return
        received_ns = time.time_ns()
        try:
            for body in bodies:
                self.recorder.record_batch(body, received_ns)
        except OSError as exc:
            logger.error("building %s: the recording cannot be written (%s)", self.building_id, exc)
            self.counters.recording_failures += 1
        self.flush_recording()

    @property
    def restore_problem(self) -> str | None:
        """Why the building's last snapshot could not be used, if it could not."""
        return self.recovery.restore_problem

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
        before = self.tracker.radio_map_id
        added = load_radio_map(self.tracker, self._config.signal_maps_dir, self.building_id)
        loaded = self.tracker.radio_map_id
        if loaded is None or loaded == before:
            return None
        self.snapshot()
        return loaded, added

    def context(self) -> convert.BuildingContext:
        """What converting a batch needs of the building now (``convert.building_context``)."""
        return convert.building_context(self.building_id, self.tracker, self.ids.index, self.geo, self.extent)

    def building_state(self) -> tracker_snapshot.BuildingState:
        """What a snapshot holds: the tracker and the building's bookkeeping, as of the last tracker call."""
        return tracker_snapshot.BuildingState(
            self.tracker,
            dict(self.ids.public),
            dict(self.ids.labels),
            dict(self._device_of_user),
            self._tracker_call,
            dict(self.history.latest_t_ms),
        )

    def snapshot(self, clear_log: bool = False) -> None:
        """Snapshot now (on load, after operator edits, at shutdown); with ``clear_log`` the bodies it
        covers are cleared in the same transaction, else a chunk per group from the next group on."""
        with self._sessions.begin() as session:
            rows = self._save_snapshot(session)
            if clear_log:
                self.recovery.clear_log(session, None)
        self.devices.saved(rows)

    def close(self) -> None:
        """Snapshot now and stop the snapshot thread (a clean stop leaves nothing to replay)."""
        self.snapshot(clear_log=True)
        self.recovery.close()

    def abandon(self) -> None:
        """Stop without writing anything: the building is another worker's now (its lease was lost)."""
        self.recovery.close()  # drops the pending snapshot unwritten

    def _save_snapshot(self, session: Session) -> list[dict[str, object]]:
        """Write the snapshot and the devices' last sequence numbers in the caller's transaction; returns the
        device rows written (the ledger counts them saved once the transaction commits)."""
        rows = self._snapshot_start(session)
        self.flush_recording()
        self.recovery.write(session, self.building_state())
        return rows

    def _periodic_snapshot(self, session: Session) -> list[dict[str, object]]:
        """In a group's transaction: write the snapshot compressed since an earlier group, or take one when
        due. Returns the device rows written."""
        if self.recovery.ready:
            self.flush_recording()
        if self.recovery.write_ready(session) or not self.recovery.due:
            return []
        rows = self._snapshot_start(session)
        self.recovery.take(self.building_state())
        return rows

    def _snapshot_start(self, session: Session) -> list[dict[str, object]]:
        """Before a snapshot: idle users forgotten, the devices' unsaved rows written."""
        self._evict_idle_users()
        rows = self.devices.unsaved_rows()
        repo.upsert_devices(session, rows)
        return rows

    def _evict_idle_users(self) -> None:
        """Forget the users not heard from for ``Retention.user_idle_s`` (right before a snapshot)."""
        idle_s = self.retention.user_idle_s
        if idle_s is None:
            return
        now = time.time()
        idle = [u for u in self.tracker.users if now - self._last_heard.setdefault(u, now) > idle_s]
        if idle:
            self.tracker.remove_users(idle)
            for u in idle:
                del self._last_heard[u]
                self.history.forget(u)
            self.counters.users_evicted += len(idle)

    # ------------------------------------------------------------------ anchors
    def anchor(self, index: int) -> BuildingAnchor:
        mean, cov, type_index, known, count, last = self.tracker.crowd.anchor(index)
        return convert.building_anchor(
            self.ids.public_id(index),
            self.building_id,
            mean,
            cov,
            type_index,
            known,
            count,
            int(last) if math.isfinite(last) and last > 0 else None,
            self.ids.labels.get(index),
            floor=self.tracker.crowd.level(index),
            signature=self.tracker.crowd.signature(index) or None,
        )

    def anchors(self) -> list[BuildingAnchor]:
        return [self.anchor(i) for i in sorted(self.ids.public) if self.tracker.crowd.is_live(i)]

    def _is_live(self, public_id: str) -> bool:
        index = self.ids.index.get(public_id)
        return index is not None and self.tracker.crowd.is_live(index)

    def get_anchor(self, public_id: str) -> BuildingAnchor:
        index = self.ids.index.get(public_id)
        if index is None or not self.tracker.crowd.is_live(index):
            raise NotFoundError(f"no anchor {public_id!r} in building {self.building_id!r}")
        return self.anchor(index)

    def put_known_anchor(
        self, public_id: str, body: KnownAnchorIn
    ) -> tuple[BuildingAnchor, list[LiveMessage]]:
        index = self.ids.index.get(public_id)
        if index is not None and not self.tracker.crowd.is_live(index):
            raise ConflictError(f"anchor {public_id!r} was deleted or merged; pick a new id")
        if self.extent is not None:
            refusal = self.extent.refusal("the anchor", body.position.x_m, body.position.y_m)
            if refusal is not None:
                raise InvalidInputError(refusal)
        if body.floor not in self.tracker.levels:
            raise InvalidInputError(
                f"building {self.building_id!r} has no floor {body.floor}; its floors: "
                f"{', '.join(map(str, self.tracker.levels))}"
            )
        xy = np.array([body.position.x_m, body.position.y_m])
        type_index = convert.anchor_type_index(body.type)
        if index is not None and self._pinned_as(index, xy, type_index, body):
            return self.anchor(index), []  # the same again (a retry): nothing changes
        index = self.tracker.pin_anchor(xy, type_index, index, level=body.floor)
        self.ids.link(index, public_id, body.label)
        anchor = self.anchor(index)
        with self._sessions.begin() as session:
            repo.save_anchor(session, anchor_row(self.building_id, anchor))
            rows = self._save_snapshot(session)
        self.devices.saved(rows)
        return anchor, [AnchorMessage(anchor=anchor)]

    def _pinned_as(self, index: int, xy: np.ndarray, type_index: int, body: KnownAnchorIn) -> bool:
        """Whether the anchor is pinned already exactly as ``body`` asks."""
        mean, _, pinned_type, known, _, _ = self.tracker.crowd.anchor(index)
        return (
            known
            and pinned_type == type_index
            and bool(np.array_equal(mean, xy))
            and self.tracker.crowd.level(index) == body.floor
            and self.ids.labels.get(index) == body.label
        )

    def delete_anchor(self, public_id: str) -> list[LiveMessage]:
        anchor = self.get_anchor(public_id)
        self.tracker.remove_anchor(self.ids.index[public_id])
        with self._sessions.begin() as session:
            repo.delete_anchor(session, self.building_id, public_id)
            rows = self._save_snapshot(session)
        self.devices.saved(rows)
        return [AnchorMessage(anchor=anchor, deleted=True)]

    def merge_anchors(self, public_ids: list[str]) -> tuple[BuildingAnchor, list[LiveMessage]]:
        if len(set(public_ids)) != len(public_ids):
            raise InvalidInputError("anchor_ids must be distinct")
        missing = [p for p in public_ids if not self._is_live(p)]
        if missing:  # the merge's target exists; the anchors it names do not (any more)
            raise ConflictError(
                f"no live anchor {', '.join(map(repr, missing))} in building {self.building_id!r}; "
                "nothing was merged"
            )
        olds = [self.get_anchor(p) for p in public_ids]
        keep = self.ids.index[public_ids[0]]
        for p in public_ids[1:]:
            self.tracker.merge_anchors(keep, self.ids.index[p])
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

    # ------------------------------------------------------------------ floor plans
    def put_floor_plan(self, level: int, body: FloorPlan) -> FloorPlan:
        """Store a floor's plan, in the local frame and within the building's extent; it weighs the steps of
        the users on that floor from the next batch on. Returns the plan as stored."""
        with self._sessions() as session:
            levels = [f.level for f in repo.list_floors(session, self.building_id)]
        if level not in levels:
            raise NotFoundError(
                f"building {self.building_id!r} has no floor {level}; its floors: "
                f"{', '.join(map(str, levels)) or 'none (create the building with floors)'}"
            )
        try:
            local = floor_plans.to_local(body, self.geo, self.extent)
            index = floor_plans.engine_plan(local)
        except ValueError as exc:
            raise InvalidInputError(f"the floor plan cannot be used: {exc}") from None
        stored = local.model_dump_json()
        with self._sessions() as session:
            if repo.floor_plan(session, self.building_id, level) == stored:
                return local  # the same plan again (a retry): nothing changes
        # the plan and a snapshot in one transaction: a restart replays the batches after it with the plan,
        # and none before it
        self.tracker.set_floor_plan(index, level)
        try:
            with self._writer_turns, self._sessions.begin() as session:
                repo.save_floor_plan(session, self.building_id, level, stored)
                rows = self._save_snapshot(session)
        except Exception:
            self.reload()  # the tracker as SQL holds it: without the plan
            raise
        self.devices.saved(rows)
        return local

    # ------------------------------------------------------------------ users
    def forget_user(self, user_id: str) -> list[LiveMessage]:
        """Forget a user, as a person may ask: its filter, its latest position and its history. A snapshot
        is written in the same transaction, so a restart does not bring the user back from the batch log;
        a later batch of its device starts a new filter. The recordings keep its batches (see the
        operations document). State changes only if the transaction commits."""
        tracked = user_id in self.tracker.users
        if tracked:
            self.tracker.remove_user(user_id)
            self._device_of_user.pop(user_id, None)
            self._last_heard.pop(user_id, None)
            self.history.forget(user_id)
        try:
            with self._writer_turns, self._sessions.begin() as session:
                deleted = repo.delete_user_positions(session, self.building_id, user_id)
                if not tracked and not deleted:
                    raise NotFoundError(f"no user {user_id!r} in building {self.building_id!r}")
                rows = self._save_snapshot(session) if tracked else []
        except NotFoundError:
            raise
        except Exception:
            if tracked:
                self.reload()  # the user's filter back, as the database still has it
            raise
        self.devices.saved(rows)
        return [UserForgottenMessage(user_id=user_id)]

    # ------------------------------------------------------------------ batches
    def assign_device(self, device_id: str, user_id: str) -> None:
        """An operator assigns a device to a user: its batches are for that user from now on."""
        row = self.devices.assign(device_id, user_id)
        with self._writer_turns, self._sessions.begin() as session:
            repo.upsert_devices(session, [row])
        self.devices.saved([row])

    def latest_estimate(self, user: str) -> Estimate | None:
        """The user's estimate, once placed (a phone started without a fix is not reported until then)."""
        row = self.tracker.estimate(user) if self.tracker.is_placed(user) else None
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
        """Apply a group of batches: dedupe, order, convert, track, persist, in one transaction.

        State changes only when that transaction commits. When it fails (a batch the engine cannot apply, a
        non-finite estimate, a database error), the building is loaded again from SQL (``reload``: what
        the tracker had changed is gone, as after a restart) and the group is applied again one batch at
        a time, so that a batch that fails fails alone and every other user of the group is served."""
        counted = dataclasses.replace(self.counters)
        try:
            return self._process(group)
        except repo.StaleStreamPositionError:
            # another worker applied these batches: this one lost the building and must not go on with it
            vars(self.counters).update(vars(counted))
            raise
        except Exception as exc:
            if is_disk_full(exc):
                # nothing of the group committed: the building as its SQL holds it, every batch refused as
                # one that may be sent again (not one batch after another: each would fail the same way)
                vars(self.counters).update(vars(counted))
                logger.error("building %s: the database's disk is full (%s)", self.building_id, exc)
                self.reload()
                self.counters.disk_full_refusals += 1
                return GroupResult([DiskFullError() for _ in group])
            logger.warning(
                "building %s: a group of %d failed (%r); reloading", self.building_id, len(group), exc
            )
            vars(self.counters).update(vars(counted))  # the metrics count what committed, like the store
            self.reload()
            if len(group) > 1:
                results: list[BatchReceipt | ProblemError] = []
                messages: list[LiveMessage] = []
                for sub in group:
                    one = self.process([sub])
                    results += one.receipts
                    messages += one.messages
                return GroupResult(results, messages)
            self.counters.failed_batches += 1
            self.counters.last_failure_unix_s = time.time()
            self._pass_over(group[0])
            if isinstance(exc, ProblemError):
                return GroupResult([exc])
            # the batch passed every check of the client's input: whatever the engine or the store raised
            # is the server's error, answered 500 without its text
            logger.exception("building %s: batch %s failed", self.building_id, group[0].header.batch_id)
            return GroupResult([BatchFailedError()])

    def _process(self, group: list[Submission]) -> GroupResult:
        ctx: convert.BuildingContext | None = None  # only for batches not converted by the front
        results: list[BatchReceipt | ProblemError | None] = [None] * len(group)
        converted: dict[int, tuple[UserBatch, list[str]]] = {}
        for i, sub in enumerate(group):
            header = sub.header
            if not self.devices.may_post_as(header.device_id, header.effective_user_id):
                bound = self.devices.user_of(header.device_id) or header.device_id
                results[i] = ForbiddenError(
                    f"device {header.device_id!r} posts as user {bound!r} or as itself, not as "
                    f"{header.effective_user_id!r} (an operator may assign it another user: PUT "
                    f"/v1/buildings/{self.building_id}/devices/{header.device_id})"
                )
                continue
            c = sub.converted
            if c is None or sub.landmarks:
                ctx = ctx or self.context()
                try:
                    if c is None:
                        assert sub.batch is not None  # a Submission holds one or the other
                        c = convert.to_user_batch(sub.batch, ctx)
                    else:  # converted by the front, but for the landmarks: only the building can place them
                        c = convert.with_landmarks(c, sub.landmarks or [], ctx)
                except ValueError as exc:
                    results[i] = InvalidInputError(str(exc))
                    continue
            converted[i] = (c.user_batch, c.warnings)
        messages: list[LiveMessage] = []
        order = list(converted)
        # late or applied, and by which tracker call, is decided before anything is written: each row goes
        # in with the call that applies it (a retry is recognised by the insert itself, and was late anyway)
        calls = dict(zip(order, self.devices.plan([group[i].header for i in order]), strict=True))
        base = self._tracker_call
        device_rows: list[dict[str, object]] = []
        to_record: list[int] = []
        estimates_to_record: list[tuple[list[Estimate], int]] = []
        with self._writer_turns, self._sessions.begin() as session:  # see server.store.writer_lock
            inserted = insert_batches_once(session, [self._accepted(group[i], calls[i], base) for i in order])
            by_call: dict[int, list[int]] = {}
            for i, row_id in zip(order, inserted, strict=True):
                b = group[i].header
                if row_id is None:
                    self.counters.duplicates += 1
                    results[i] = self._receipt(b, "duplicate", converted[i][1])
                    continue
                to_record.append(i)
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
            streamed = [sub.stream_sequence for sub in group if sub.stream_sequence is not None]
            if streamed:
                repo.advance_stream_position(session, self.building_id, max(streamed))
            # a user may have several batches in one group: one per user per tracker call
            for call in sorted(by_call):
                now = by_call[call]
                self._tracker_call = base + call
                applied = self._apply(session, group, converted, now)
                for i, receipt in applied.receipts.items():
                    results[i] = receipt
                messages += applied.messages
                estimates_to_record.append((applied.estimates, group[now[0]].received_ns))
            device_rows += self._periodic_snapshot(session)
            self.recovery.clear_log(session, max(1, int(self.retention.log_clear_per_batch * len(group))))
            if time.monotonic() - self._last_prune >= self.retention.prune_period_s:
                self._prune(session)
        self.devices.saved(device_rows)
        # recorded once committed: a batch whose transaction failed is not in the recording (a crash between
        # the commit and these writes leaves an acknowledged batch out of it, never a refused one in)
        if self.recorder is not None:
            self._record([group[i] for i in to_record], estimates_to_record)
        self.counters.batches += len(group)
        return GroupResult([r if r is not None else ProblemError("not processed") for r in results], messages)

    def _apply(
        self,
        session: Session,
        group: list[Submission],
        converted: dict[int, tuple[UserBatch, list[str]]],
        now: list[int],
    ) -> _Applied:
        """One tracker call over the batches ``now`` (indices into ``group``, at most one per user): their
        positions and anchor changes written in ``session``; their receipts, the live messages, and the
        estimates to record once the transaction commits."""
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
        messages: list[LiveMessage] = []
        stored_at_ms = int(heard * 1000)
        rows = [position_row(self.building_id, e, stored_at_ms) for e in estimates.values()]
        repo.add_positions(session, rows, [self.history.joins(e.user_id, e.t_ms) for e in estimates.values()])
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
        receipts: dict[int, BatchReceipt] = {}
        for i in now:
            b = group[i].header
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
            if report.clock_restarted:
                warnings.append(
                    "every time in this batch is over a minute behind the user's last one: the phone's clock "
                    "went back, and its timeline restarts at this batch"
                )
            if report.steps_dropped:
                warnings.append(_dropped_warning(report.steps_dropped, report.status))
            receipts[i] = self._receipt(
                b, "applied", warnings, estimates.get(b.effective_user_id), by_user.get(b.effective_user_id)
            )
        return _Applied(receipts, messages, list(estimates.values()))

    def _record(self, batches: list[Submission], estimates: list[tuple[list[Estimate], int]]) -> None:
        """Write the group's accepted batches and its estimates to the recording, and delete the recordings
        past their retention (every ``RECORDING_PRUNE_S``). A recording that cannot be written (a full disk)
        is logged and counted: the batches are acknowledged all the same, their log is in SQL."""
        assert self.recorder is not None
        try:
            for sub in batches:
                self.recorder.record_batch(sub.raw, sub.received_ns)
            for rows, received_ns in estimates:
                self.recorder.record_estimates(rows, received_ns)
            self.recorder.flush()
        except OSError as exc:
            if not self.counters.recording_failures:
                logger.error("building %s: the recording cannot be written (%s)", self.building_id, exc)
            self.counters.recording_failures += 1
        r = self.retention
        now = time.monotonic()
        if (
            r.recording_days or r.recording_max_bytes
        ) and now - self._last_recording_prune >= RECORDING_PRUNE_S:
            self._last_recording_prune = now
            max_age = None if r.recording_days is None else r.recording_days * 86_400
            pruned = prune_recordings(self.recorder.root, max_age, r.recording_max_bytes, time.time())
            self.counters.pruned_recordings += pruned.files

    def idle(self) -> None:
        """Called when no batch has come for ``IDLE_S``: the recording's chunk in progress is written, so that
        a building gone quiet loses at most seconds of recording in a crash, and a build reads all of it."""
        self.flush_recording()

    def flush_recording(self) -> None:
        """Write the recording's chunk in progress now (before a signal-map build reads the recordings)."""
        if self.recorder is None:
            return
        try:
            self.recorder.flush(now=True)
        except OSError as exc:
            logger.error("building %s: the recording cannot be written (%s)", self.building_id, exc)
            self.counters.recording_failures += 1

    def _pass_over(self, sub: Submission) -> None:
        """A streamed batch that failed alone is still passed in the stream, so that the next owner of the
        building does not apply it again (its answer would be the same failure)."""
        if sub.stream_sequence is None:
            return
        with self._sessions.begin() as session:
            repo.advance_stream_position(session, self.building_id, sub.stream_sequence)

    def _prune(self, session: Session) -> None:
        """Delete a chunk of position history and of batch ids past their retention."""
        r = self.retention
        now = time.time()
        positions_before = (
            None if r.position_history_days is None else int((now - r.position_history_days * 86_400) * 1e3)
        )
        batches_before = (
            None
            if r.batch_ids_hours is None
            else datetime.fromtimestamp(now - r.batch_ids_hours * 3_600, UTC)
        )
        positions, batches = repo.prune_history(
            session, self.building_id, positions_before, batches_before, r.prune_chunk
        )
        self.counters.pruned_positions += positions
        self.counters.pruned_batches += batches
        self.counters.reclaimed_pages += reclaim_free_pages(session, RECLAIM_PAGES)
        self._last_prune = time.monotonic()

    def _accepted(self, sub: Submission, call: int | None, base: int) -> AcceptedBatch:
        span = sub.header.span_ms
        return AcceptedBatch(
            self.building_id,
            sub.header.device_id,
            sub.header.batch_id,
            sub.header.seq,
            None if span is None else span[0],
            None if span is None else span[1],
            len(sub.raw),
            None if call is None else sub.raw,  # a late batch is never replayed: nothing to log
            None if call is None else base + call,
        )

    def _receipt(
        self,
        batch: BatchHeader,
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
            tracking=self.tracker.is_placed(user),
            estimate=estimate,
            encounters=encounters or [],
            warnings=warnings,
        )


@dataclass(frozen=True)
class _Applied:
    """What one tracker call over a group's batches gives: their receipts (by index in the group), the live
    messages, and the estimates to record."""

    receipts: dict[int, BatchReceipt]
    messages: list[LiveMessage]
    estimates: list[Estimate]


def _dropped_warning(n: int, status: str) -> str:
    if status != "tracking":
        return (
            f"{n} steps skipped: the user has no position yet (send a fix, a tag or a known-anchor reading; "
            "or WiFi scans, which place the phone where the crowd's map knows the place)"
        )
    return f"{n} steps skipped: out of time order, or turns without any azimuth to start from"


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
