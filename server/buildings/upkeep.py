"""A building's upkeep beside its batches: its recording (each group's batches and estimates, written once
committed; what a restart replays, written again; flushed when the building goes quiet and before each
snapshot), and the history SQL and the recordings keep (``Retention``), pruned a chunk at a time."""

from __future__ import annotations

import logging
import math
import time
from datetime import UTC, datetime

from sqlalchemy.orm import Session

from schemas.estimates import Estimate
from server.buildings.building import Building
from server.buildings.submissions import Submission
from server.recordings.recorder import prune_recordings
from server.store import repositories as repo
from server.store.db import reclaim_free_pages

logger = logging.getLogger(__name__)

RECORDING_PRUNE_S = 60.0
"""How often a building deletes the recordings past their retention (a listing of every building's files)."""
RECLAIM_PAGES = 2048
"""At most this many free SQLite pages (8 MB of 4 KiB pages) handed back per prune."""


class Upkeep:
    def __init__(self, building: Building) -> None:
        self.building = building
        self._last_prune = -math.inf
        self._last_recording_prune = -math.inf

    # ------------------------------------------------------------------ the recording
    def record(self, batches: list[Submission], estimates: list[tuple[list[Estimate], int]]) -> None:
        """Write a group's accepted batches and its estimates to the recording, once its transaction has
        committed, and delete the recordings past their retention (every ``RECORDING_PRUNE_S``). A
        recording that cannot be written (a full disk) is logged and counted: the batches are acknowledged
        all the same, their log is in SQL."""
        b = self.building
        if b.recorder is None:
            return
        try:
            for sub in batches:
                b.recorder.record_batch(sub.raw, sub.received_ns)
            for rows, received_ns in estimates:
                b.recorder.record_estimates(rows, received_ns)
            b.recorder.flush()
        except OSError as exc:
            self._cannot_record(exc)
        r = b.config.retention
        now = time.monotonic()
        kept = r.recording_days or r.recording_max_bytes
        if kept and now - self._last_recording_prune >= RECORDING_PRUNE_S:
            self._last_recording_prune = now
            max_age = None if r.recording_days is None else r.recording_days * 86_400
            pruned = prune_recordings(b.recorder.root, max_age, r.recording_max_bytes, time.time())
            b.counters.pruned_recordings += pruned.files

    def record_again(self, bodies: list[bytes]) -> None:
        """Record the batches a load replayed: a crash may have cut them from the recordings (those a
        snapshot covers are in them: they were flushed before it was written)."""
        b = self.building
        if b.recorder is None or not bodies:
            return
        received_ns = time.time_ns()
        try:
            for body in bodies:
                b.recorder.record_batch(body, received_ns)
        except OSError as exc:
            self._cannot_record(exc)
        self.flush_recording()

    def flush_recording(self) -> None:
        """Write the recording's chunk in progress now (before a snapshot, before a signal-map build reads
        the recordings, when the building goes quiet)."""
        b = self.building
        if b.recorder is None:
            return
        try:
            b.recorder.flush(now=True)
        except OSError as exc:
            self._cannot_record(exc)

    def idle(self) -> None:
        """No batch has come for a while: the recording's chunk in progress is written, so that a building
        gone quiet loses at most seconds of recording in a crash, and a build reads all of it."""
        self.flush_recording()

    def _cannot_record(self, exc: OSError) -> None:
        b = self.building
        if not b.counters.recording_failures:
            logger.error("building %s: the recording cannot be written (%s)", b.building_id, exc)
        b.counters.recording_failures += 1

    # ------------------------------------------------------------------ retention in SQL
    def prune_if_due(self, session: Session) -> None:
        """In a group's transaction, at most every ``Retention.prune_period_s``: delete a chunk of position
        history (and the zone visits of its time) and of batch ids past their retention, and hand free SQLite
        pages back."""
        b = self.building
        r = b.config.retention
        if time.monotonic() - self._last_prune < r.prune_period_s:
            return
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
            session, b.building_id, positions_before, batches_before, r.prune_chunk
        )
        b.counters.pruned_positions += positions
        if positions_before is not None:  # zone visits are kept as long as the positions they came from
            b.counters.pruned_visits += repo.prune_visits(
                session, b.building_id, positions_before, r.prune_chunk
            )
        b.counters.pruned_batches += batches
        b.counters.reclaimed_pages += reclaim_free_pages(session, RECLAIM_PAGES)
        self._last_prune = time.monotonic()
