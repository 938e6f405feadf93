"""Repository of accepted batches. Retries are detected by the unique constraint, never check-then-insert."""

from __future__ import annotations

from dataclasses import dataclass

import zstandard
from sqlalchemy import delete, insert, select
from sqlalchemy.orm import Session

from server.store.db import execute_many, insert_many_once
from server.store.models import BatchLogRow, BatchRow, TrackerSnapshotRow

LOG_ZSTD_LEVEL = 1
"""The logged bodies are zstd frames at this level: a load-benchmark batch of ~1,050 B of JSON is logged in
~290 B for ~5 us of CPU (levels 1 and 3 differ by 2 B; zlib's fastest takes twice the time for the same
size). The log is written with every batch and deleted once a snapshot covers it, so what this saves is the
bytes every batch writes to the database and its write-ahead log."""

_ZSTD_FRAME = b"\x28\xb5\x2f\xfd"
"""How a zstd frame starts. A batch's JSON starts with ``{`` or white space, so a logged body says which it
is: a body logged uncompressed (by a version before compression) is read as it is."""


@dataclass(frozen=True)
class AcceptedBatch:
    building_id: str
    device_id: str
    batch_id: str
    seq: int
    t_first_ms: int | None
    t_last_ms: int | None
    n_bytes: int
    body: bytes | None = None
    """The batch as posted, logged (``batch_log``) until a tracker snapshot covers it; None when nothing
    will apply it."""
    tracker_call: int | None = None
    """The building's tracker call that applies it (the order a restart replays the log in); None: late."""


@dataclass(frozen=True)
class LoggedBatch:
    row_id: int
    tracker_call: int
    body: bytes


def insert_batches_once(session: Session, batches: list[AcceptedBatch]) -> list[int | None]:
    """Insert many batches, one statement for their ids and one for the bodies of those newly inserted that
    will be applied (the log); each one's row id, or None for a retry (already stored, or repeated earlier
    in ``batches``). Same atomic decision as ``insert_batch_once``."""
    ids = {
        (device, batch_id): int(row_id)
        for row_id, device, batch_id in insert_many_once(
            session,
            BatchRow,
            [_values(b) for b in batches],
            ["building_id", "device_id", "batch_id"],
            [BatchRow.id, BatchRow.device_id, BatchRow.batch_id],
        )
    }
    out: list[int | None] = []
    logged = []
    compressor = zstandard.ZstdCompressor(level=LOG_ZSTD_LEVEL)  # one a call: a compressor is not shared
    for b in batches:
        row_id = ids.pop((b.device_id, b.batch_id), None)  # a repeat within the group gets None
        out.append(row_id)
        if row_id is not None and b.body is not None and b.tracker_call is not None:
            logged.append(
                {
                    "batch_row_id": row_id,
                    "building_id": b.building_id,
                    "tracker_call": b.tracker_call,
                    "body": compressor.compress(b.body),
                }
            )
    execute_many(session, _LOG_INSERT, logged)
    return out


_LOG_INSERT = insert(BatchLogRow)


def _values(batch: AcceptedBatch) -> dict[str, object]:
    return {
        "building_id": batch.building_id,
        "device_id": batch.device_id,
        "batch_id": batch.batch_id,
        "seq": batch.seq,
        "t_first_ms": batch.t_first_ms,
        "t_last_ms": batch.t_last_ms,
        "n_bytes": batch.n_bytes,
        "applied": batch.tracker_call is not None,
        "tracker_call": batch.tracker_call,
    }


def insert_batch_once(session: Session, batch: AcceptedBatch) -> int | None:
    """Insert the batch and return its row id, or None when (building, device, batch id) already exists.

    ``INSERT ... ON CONFLICT DO NOTHING`` makes the database decide atomically, so two concurrent retries
    of one batch cannot both be accepted.
    """
    return insert_batches_once(session, [batch])[0]


def clear_covered_bodies(session: Session, building_id: str, limit: int | None = None) -> int:
    """Delete the logged bodies of a building's batches that its tracker snapshot covers (applied by engine
    calls up to the snapshot's round). The snapshot's round is read in the same statement, so nothing is
    deleted that the snapshot in SQL does not cover. At most ``limit`` rows when given: a building applying
    thousands of batches a minute clears its log a chunk per group instead of in one long statement.
    Returns how many bodies went."""
    session.flush()  # a snapshot saved in this transaction through the ORM is what the statement reads
    snapshot_call = (
        select(TrackerSnapshotRow.tracker_call)
        .where(TrackerSnapshotRow.building_id == building_id)
        .scalar_subquery()
    )
    covered = (BatchLogRow.building_id == building_id, BatchLogRow.tracker_call <= snapshot_call)
    if limit is None:
        stmt = delete(BatchLogRow).where(*covered)
    else:
        doomed = select(BatchLogRow.batch_row_id).where(*covered).limit(limit).scalar_subquery()
        stmt = delete(BatchLogRow).where(BatchLogRow.batch_row_id.in_(doomed))
    return int(session.connection().execute(stmt).rowcount or 0)


def logged_batches(session: Session, building_id: str, after_call: int | None = None) -> list[LoggedBatch]:
    """The applied batches still logged, in the order they were applied: those of tracker calls after
    ``after_call`` (the tracker call of the snapshot they are replayed onto; older bodies the snapshot
    covers may not be cleared yet), or all when None."""
    stmt = (
        select(BatchLogRow.batch_row_id, BatchLogRow.tracker_call, BatchLogRow.body)
        .where(BatchLogRow.building_id == building_id)
        .order_by(BatchLogRow.tracker_call, BatchLogRow.batch_row_id)
    )
    if after_call is not None:
        stmt = stmt.where(BatchLogRow.tracker_call > after_call)
    decompressor = zstandard.ZstdDecompressor()
    return [
        LoggedBatch(int(i), int(r), _logged_body(decompressor, bytes(b))) for i, r, b in session.execute(stmt)
    ]


def _logged_body(decompressor: zstandard.ZstdDecompressor, stored: bytes) -> bytes:
    """A logged body as posted: decompressed, or as it is when it was logged uncompressed."""
    if stored.startswith(_ZSTD_FRAME):
        body: bytes = decompressor.decompress(stored)
        return body
    return stored


def find_batch(session: Session, building_id: str, device_id: str, batch_id: str) -> BatchRow | None:
    stmt = select(BatchRow).where(
        BatchRow.building_id == building_id, BatchRow.device_id == device_id, BatchRow.batch_id == batch_id
    )
    return session.execute(stmt).scalar_one_or_none()
