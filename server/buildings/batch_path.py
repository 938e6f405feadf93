"""The path of one group of batches through a building: dedupe by the batch rows' unique constraint, order
each device's batches, convert them, apply them to the tracker, write the batch rows, the log, the anchor-map
deltas, the positions and the zone visits in one transaction, record them once it commits, and answer each
batch. A group that fails is applied again one batch at a time from the building as SQL holds it, so that a
batch that fails fails alone (``docs/architecture.md``)."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol

from sqlalchemy.orm import Session

from schemas.api import BatchReceipt
from schemas.estimates import EncounterEvent, Estimate
from schemas.live import AnchorMessage, EncounterMessage, LiveMessage, PositionMessage
from server.buildings.building import Building
from server.buildings.rows import anchor_row, position_row
from server.buildings.submissions import BatchHeader, GroupResult, Submission
from server.buildings.upkeep import Upkeep
from server.buildings.users import Users
from server.buildings.zones import Zones
from server.errors import (
    BatchFailedError,
    DiskFullError,
    ForbiddenError,
    InvalidInputError,
    ProblemError,
)
from server.ingestion import convert, transport
from server.store import repositories as repo
from server.store.batches import AcceptedBatch, insert_batches_once
from server.store.db import is_disk_full
from slam_core.tracking.tracker import UserBatch

logger = logging.getLogger(__name__)


class GroupSnapshots(Protocol):
    """What the batch path asks of the building's snapshots in a group's transaction
    (``BuildingHost``)."""

    def periodic(self, session: Session, group_size: int) -> list[dict[str, object]]:
        """Write the snapshot compressed since an earlier group or take one when due, and clear a chunk of
        the logged bodies a snapshot covers; the device rows written."""
        ...


class BatchPath:
    def __init__(
        self,
        building: Building,
        users: Users,
        zones: Zones,
        upkeep: Upkeep,
        snapshots: GroupSnapshots,
        reload: Callable[[], None],
    ) -> None:
        self.building = building
        self._users = users
        self._zones = zones
        self._upkeep = upkeep
        self._snapshots = snapshots
        self._reload = reload

    def process(self, group: list[Submission]) -> GroupResult:
        """Apply a group of batches: dedupe, order, convert, track, persist, in one transaction.

        State changes only when that transaction commits. When it fails (a batch the engine cannot apply, a
        non-finite estimate, a database error), the building is loaded again from SQL (``reload``: what
        the tracker had changed is gone, as after a restart) and the group is applied again one batch at
        a time, so that a batch that fails fails alone and every other user of the group is served."""
        b = self.building
        counted = dataclasses.replace(b.counters)
        try:
            return self._process(group)
        except repo.StaleStreamPositionError:
            # another cluster worker applied these batches: this one lost the building and must not go on
            vars(b.counters).update(vars(counted))
            raise
        except Exception as exc:
            if is_disk_full(exc):
                # nothing of the group committed: the building as its SQL holds it, every batch refused as
                # one that may be sent again (not one batch after another: each would fail the same way)
                vars(b.counters).update(vars(counted))
                logger.error("building %s: the database's disk is full (%s)", b.building_id, exc)
                self._reload()
                b.counters.disk_full_refusals += 1
                return GroupResult([DiskFullError() for _ in group])
            logger.warning(
                "building %s: a group of %d failed (%r); reloading", b.building_id, len(group), exc
            )
            vars(b.counters).update(vars(counted))  # the metrics count what committed, like the store
            self._reload()
            if len(group) > 1:
                results: list[BatchReceipt | ProblemError] = []
                messages: list[LiveMessage] = []
                for sub in group:
                    one = self.process([sub])
                    results += one.receipts
                    messages += one.messages
                return GroupResult(results, messages)
            b.counters.failed_batches += 1
            b.counters.last_failure_unix_s = time.time()
            self._pass_over(group[0])
            if isinstance(exc, ProblemError):
                return GroupResult([exc])
            # the batch passed every check of the client's input: whatever the engine or the store raised
            # is the server's error, answered 500 without its text
            logger.exception("building %s: batch %s failed", b.building_id, group[0].header.batch_id)
            return GroupResult([BatchFailedError()])

    def _process(self, group: list[Submission]) -> GroupResult:
        b = self.building
        ctx: convert.BuildingContext | None = None  # made once a group, for the batches with landmarks
        results: list[BatchReceipt | ProblemError | None] = [None] * len(group)
        converted: dict[int, tuple[UserBatch, list[str]]] = {}
        for i, sub in enumerate(group):
            header = sub.header
            if not b.devices.may_post_as(header.device_id, header.effective_user_id):
                bound = b.devices.user_of(header.device_id) or header.device_id
                results[i] = ForbiddenError(
                    f"device {header.device_id!r} posts as user {bound!r} or as itself, not as "
                    f"{header.effective_user_id!r} (an operator may assign it another user: PUT "
                    f"/v1/buildings/{b.building_id}/devices/{header.device_id})"
                )
                continue
            try:
                if sub.landmarks:  # only the building can place them: its frame, extent, floors, anchors
                    ctx = ctx or b.context()
                    c = convert.placed(sub.columns, sub.landmarks, ctx)
                else:
                    c = convert.Converted(transport.unpack(sub.columns), [])
            except ValueError as exc:
                results[i] = InvalidInputError(str(exc))
                continue
            converted[i] = (c.user_batch, c.warnings)
        messages: list[LiveMessage] = []
        order = list(converted)
        # late or applied, and by which tracker call, is decided before anything is written: each row goes
        # in with the call that applies it (a retry is recognised by the insert itself, and was late anyway)
        calls = dict(zip(order, b.devices.plan([group[i].header for i in order]), strict=True))
        base = b.tracker_call
        device_rows: list[dict[str, object]] = []
        to_record: list[int] = []
        estimates_to_record: list[tuple[list[Estimate], int]] = []
        with b.writer_turns, b.sessions.begin() as session:  # see server.store.writer_turns
            inserted = insert_batches_once(session, [self._accepted(group[i], calls[i], base) for i in order])
            by_call: dict[int, list[int]] = {}
            for i, row_id in zip(order, inserted, strict=True):
                header = group[i].header
                if row_id is None:
                    b.counters.duplicates += 1
                    results[i] = self._receipt(header, "duplicate", converted[i][1])
                    continue
                to_record.append(i)
                call = calls[i]
                if call is None:
                    b.counters.late += 1
                    results[i] = self._receipt(header, "late", converted[i][1])
                    continue
                b.device_of_user[header.effective_user_id] = header.device_id
                row = b.devices.applied(header)
                if row is not None:
                    device_rows.append(row)
                by_call.setdefault(call, []).append(i)
            repo.upsert_devices(session, device_rows)
            streamed = [sub.stream_sequence for sub in group if sub.stream_sequence is not None]
            if streamed:
                repo.advance_stream_position(session, b.building_id, max(streamed))
            # a user may have several batches in one group: one per user per tracker call
            for call in sorted(by_call):
                now = by_call[call]
                b.tracker_call = base + call
                applied = self._apply(session, group, converted, now)
                for i, receipt in applied.receipts.items():
                    results[i] = receipt
                messages += applied.messages
                estimates_to_record.append((applied.estimates, group[now[0]].received_ns))
            device_rows += self._snapshots.periodic(session, len(group))
            self._upkeep.prune_if_due(session)
        b.devices.saved(device_rows)
        messages += b.take_told()
        # recorded once committed: a batch whose transaction failed is not in the recording (one acknowledged
        # but cut from it by a crash is recorded again when the building loads and replays it)
        self._upkeep.record([group[i] for i in to_record], estimates_to_record)
        b.counters.batches += len(group)
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
        b = self.building
        outcome = b.tracker.apply([converted[i][0] for i in now])
        self._users.heard([converted[i][0].user for i in now])
        encounters = [convert.encounter_event(e, b.building_id) for e in outcome.encounters]
        b.counters.encounters += len(encounters)
        b.counters.encounters_applied += sum(e.applied for e in encounters)
        b.counters.encounter_detections += outcome.detections
        estimates = {u: b.estimate(u, row) for u, row in outcome.estimates.items()}
        b.counters.estimates += len(estimates)
        messages: list[LiveMessage] = []
        stored_at_ms = int(time.time() * 1000)
        rows = [position_row(b.building_id, e, stored_at_ms) for e in estimates.values()]
        repo.add_positions(session, rows, [b.history.joins(e.user_id, e.t_ms) for e in estimates.values()])
        for index in outcome.anchors_changed:
            if b.tracker.crowd.is_live(index):
                anchor = b.anchor(index)
                repo.save_anchor(session, anchor_row(b.building_id, anchor))
                messages.append(AnchorMessage(anchor=anchor))
        messages += [PositionMessage(estimate=e) for e in estimates.values()]
        messages += [EncounterMessage(encounter=e) for e in encounters]
        messages += self._zones.record(session, outcome.zone_events)
        by_user: dict[str, list[EncounterEvent]] = {}
        for e in encounters:
            by_user.setdefault(e.user_a, []).append(e)
            if e.user_b != e.user_a:
                by_user.setdefault(e.user_b, []).append(e)
        receipts: dict[int, BatchReceipt] = {}
        for i in now:
            header = group[i].header
            report = outcome.reports[converted[i][0].user]
            b.counters.steps_dropped += report.steps_dropped
            b.counters.steps_detected += report.steps_detected
            b.counters.imu_samples_dropped += report.imu_samples_dropped
            b.counters.recentred += report.recentred
            b.counters.fingerprint_fixes += report.fingerprint_fixes
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
            user = header.effective_user_id
            receipts[i] = self._receipt(header, "applied", warnings, estimates.get(user), by_user.get(user))
        return _Applied(receipts, messages, list(estimates.values()))

    def _pass_over(self, sub: Submission) -> None:
        """A streamed batch that failed alone is still passed in the stream, so that the next owner of the
        building does not apply it again (its answer would be the same failure)."""
        b = self.building
        if sub.stream_sequence is None:
            return
        with b.sessions.begin() as session:
            repo.advance_stream_position(session, b.building_id, sub.stream_sequence)

    def _accepted(self, sub: Submission, call: int | None, base: int) -> AcceptedBatch:
        b = self.building
        span = sub.header.span_ms
        return AcceptedBatch(
            b.building_id,
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
        b = self.building
        user = batch.effective_user_id
        if estimate is None:
            estimate = b.latest_estimate(user)
        return BatchReceipt(
            batch_id=batch.batch_id,
            status=status,
            duplicate=status == "duplicate",
            tracking=b.tracker.is_placed(user),
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
