"""A building's tracking state as bytes, for crash recovery.

The snapshot is the whole ``BuildingTracker`` (every user's particles and maps, the crowd map and graph, the
encounter detector, the random streams) plus the session's bookkeeping (public anchor ids, labels, the
device of each user, the engine-call counter), pickled and compressed. Together with the batch bodies
logged since (in the batches table, same transaction as the acknowledgement), it restores tracking
exactly: replaying the log in its original engine calls gives bit-identical filters (tested).

Pickle is used because the state is numpy arrays and plain containers owned by this code, written and
read only by this server's database; a snapshot written by another code version or other tracker
parameters is refused (``SnapshotMismatchError``) and the building starts from its SQL anchor map instead.
"""

from __future__ import annotations

import pickle
import zlib
from dataclasses import dataclass

from slam_core.encounters import Calibration
from slam_core.tracker import BuildingTracker, TrackerParams

FORMAT_VERSION = 6
"""Bump when BuildingTracker's attributes change: old snapshots are then refused, not misread."""


class SnapshotMismatchError(ValueError):
    """The stored snapshot cannot be used by this server (format or parameters differ, or it is corrupt)."""


@dataclass
class SessionState:
    tracker: BuildingTracker
    public_ids: dict[int, str]
    labels: dict[int, str | None]
    device_of_user: dict[str, str]
    applied_round: int


def encode(state: SessionState) -> bytes:
    return zlib.compress(pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL), 1)


def decode(blob: bytes, format_version: int, params: TrackerParams, calibration: Calibration) -> SessionState:
    if format_version != FORMAT_VERSION:
        raise SnapshotMismatchError(f"snapshot format {format_version}, this server reads {FORMAT_VERSION}")
    try:
        state = pickle.loads(zlib.decompress(blob))
    except (zlib.error, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as exc:
        raise SnapshotMismatchError(f"snapshot unreadable: {exc}") from exc
    if not isinstance(state, SessionState) or not isinstance(state.tracker, BuildingTracker):
        raise SnapshotMismatchError("snapshot does not hold a building's tracking state")
    if repr(state.tracker.params) != repr(params):
        raise SnapshotMismatchError("snapshot was taken with other tracker parameters")
    if state.tracker.detector.calibration.to_dict() != calibration.to_dict():
        raise SnapshotMismatchError("snapshot was taken with another encounter calibration")
    return state
