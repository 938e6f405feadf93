"""A building's tracking state as bytes, for crash recovery.

The snapshot is the whole ``BuildingTracker`` (every user's particles and maps, the crowd map and graph, the
encounter detector, the random streams) plus the building's bookkeeping (public anchor ids, labels, the
device of each user, the engine-call counter), pickled and compressed. Together with the batch bodies
logged since (in the batches table, same transaction as the acknowledgement), it restores tracking
exactly: replaying the log in its original tracker calls gives bit-identical filters (tested).

Pickle is used because the state is numpy arrays and plain containers owned by this code, written and
read only by this server's database; a snapshot written by another code version or other tracker
parameters is refused (``SnapshotMismatchError``) and the building starts from its SQL anchor map instead.
"""

from __future__ import annotations

import gc
import pickle
import zlib
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

from slam_core.encounters.models import Calibration
from slam_core.tracking.tracker import BuildingTracker, TrackerParams

FORMAT_VERSION = 22
"""Bump when BuildingTracker's attributes change, or a pickled class moves to another module: old snapshots
are then refused, not misread."""


class SnapshotMismatchError(ValueError):
    """The stored snapshot cannot be used by this server (format or parameters differ, or it is corrupt)."""


@dataclass
class BuildingState:
    tracker: BuildingTracker
    public_ids: dict[int, str]
    labels: dict[int, str | None]
    device_of_user: dict[str, str]
    tracker_call: int
    history_t_ms: dict[str, int] = field(default_factory=dict)
    """Each user's latest row of position history (``server.buildings.rows.HistorySampling``); snapshots of
    an earlier server have none (read with ``getattr``), and the sampling starts over."""


def encode(state: BuildingState) -> bytes:
    return _compress(pickled(state))


def pickled(state: BuildingState) -> bytes:
    """The state as bytes, before compression (the part of a snapshot that holds the building's thread).
    The cyclic collector is paused meanwhile: pickling makes many short-lived objects, and the collections
    they would set off only slow it down."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        return pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)
    finally:
        if collecting:
            gc.enable()


def _compress(raw: bytes) -> bytes:
    return zlib.compress(raw, 1)


class BackgroundSnapshots:
    """Periodic snapshots compressed off the batch path.

    The state is pickled where it is consistent (the building's thread, between groups), but compressing
    it takes longer again, and far more with full particle maps: zlib releases the GIL, so it runs on a
    thread of its own while the building applies the
    next groups. The blob is then written by a later group's transaction (``ready``); from then on the
    logged batch bodies up to the snapshot's tracker call are cleared a chunk per group: the batches
    applied meanwhile stay logged, and a crash in between restarts from the previous snapshot and the
    batches logged after it."""

    def __init__(self, building_id: str) -> None:
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"snapshot-{building_id}")
        self._pending: tuple[int, Future[bytes]] | None = None

    @property
    def pending(self) -> bool:
        return self._pending is not None

    @property
    def ready_to_write(self) -> bool:
        """Whether ``ready`` would give the pending snapshot (or raise its failure) now."""
        return self._pending is not None and self._pending[1].done()

    def take(self, state: BuildingState) -> None:
        """Pickle the state now and compress it in the background (at most one at a time)."""
        if self._pending is not None:
            raise RuntimeError("a snapshot is already being compressed")
        raw = pickled(state)
        self._pending = (state.tracker_call, self._executor.submit(_compress, raw))

    def ready(self) -> tuple[int, bytes] | None:
        """The pending snapshot's tracker call and blob once compressed (then no longer pending); None while
        it is still being compressed or when none is. A failure to compress is raised once, and forgotten."""
        if self._pending is None or not self._pending[1].done():
            return None
        tracker_call, future = self._pending
        self._pending = None
        return tracker_call, future.result()

    def wait(self) -> None:
        """Block until the pending snapshot (if any) is compressed, so that the next group writes it."""
        if self._pending is not None:
            self._pending[1].exception()

    def discard(self) -> None:
        """Forget the pending snapshot (a newer one is being written now)."""
        if self._pending is not None:
            self._pending[1].cancel()
            self._pending = None

    def close(self) -> None:
        self.discard()
        self._executor.shutdown(wait=True)


def decode(
    blob: bytes, format_version: int, params: TrackerParams, calibration: Calibration
) -> BuildingState:
    if format_version != FORMAT_VERSION:
        raise SnapshotMismatchError(f"snapshot format {format_version}, this server reads {FORMAT_VERSION}")
    try:
        state = pickle.loads(zlib.decompress(blob))
    except (zlib.error, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as exc:
        raise SnapshotMismatchError(f"snapshot unreadable: {exc}") from exc
    if not isinstance(state, BuildingState) or not isinstance(state.tracker, BuildingTracker):
        raise SnapshotMismatchError("snapshot does not hold a building's tracking state")
    if repr(state.tracker.params) != repr(params):
        raise SnapshotMismatchError("snapshot was taken with other tracker parameters")
    if state.tracker.encounters.detector.calibration.to_dict() != calibration.to_dict():
        raise SnapshotMismatchError("snapshot was taken with another encounter calibration")
    return state
