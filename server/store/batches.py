"""Repository of accepted batches. Retries are detected by the unique constraint, never check-then-insert."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.store.db import insert_once
from server.store.models import BatchRow


@dataclass(frozen=True)
class AcceptedBatch:
    building_id: str
    device_id: str
    batch_id: str
    seq: int
    t_first_ms: int | None
    t_last_ms: int | None
    n_bytes: int


def insert_batch_once(session: Session, batch: AcceptedBatch) -> int | None:
    """Insert the batch and return its row id, or None when (building, device, batch id) already exists.

    ``INSERT ... ON CONFLICT DO NOTHING`` makes the database decide atomically, so two concurrent retries
    of one batch cannot both be accepted.
    """
    values = {
        "building_id": batch.building_id,
        "device_id": batch.device_id,
        "batch_id": batch.batch_id,
        "seq": batch.seq,
        "t_first_ms": batch.t_first_ms,
        "t_last_ms": batch.t_last_ms,
        "n_bytes": batch.n_bytes,
        "applied": False,
    }
    row_id = insert_once(session, BatchRow, values, ["building_id", "device_id", "batch_id"], BatchRow.id)
    return int(row_id) if row_id is not None else None


def mark_applied(session: Session, row_id: int) -> None:
    row = session.get(BatchRow, row_id)
    if row is None:
        raise LookupError(f"no accepted batch with id {row_id}")
    row.applied = True


def find_batch(session: Session, building_id: str, device_id: str, batch_id: str) -> BatchRow | None:
    stmt = select(BatchRow).where(
        BatchRow.building_id == building_id, BatchRow.device_id == device_id, BatchRow.batch_id == batch_id
    )
    return session.execute(stmt).scalar_one_or_none()
