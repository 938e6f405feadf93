"""A batch as it goes to its building (its header, the validated or converted batch), and what a group of
batches gives back."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

from schemas.api import BatchReceipt
from schemas.live import LiveMessage
from schemas.sensors import SensorBatch
from server.errors import ProblemError
from server.ingestion.convert import Converted


class BatchHeader(NamedTuple):
    """What the batch path needs of a batch besides its sensor arrays: who sent it, and its place among
    that device's batches (a plain tuple: it crosses the socket to a building's process with each batch)."""

    device_id: str
    effective_user_id: str
    batch_id: str
    seq: int
    ble_advertised_id: str | None
    span_ms: tuple[int, int] | None
    """First and last sensor time in the batch, None for an empty batch."""
    install_ms: int | None = None
    """The app's install time on the phone: ``seq`` counts within it (``server.buildings.ledger``)."""

    @classmethod
    def of(cls, batch: SensorBatch) -> BatchHeader:
        return cls(
            batch.device_id,
            batch.effective_user_id,
            batch.batch_id,
            batch.seq,
            batch.ble_advertised_id,
            batch.time_span_ms(),
            batch.install_ms,
        )


@dataclass(frozen=True)
class Submission:
    """One accepted batch for its building: the validated batch, or, from the front of a building's own
    process, the batch converted already (``server.ingestion.transport``)."""

    header: BatchHeader
    raw: bytes  # the body as posted, for the recording
    received_ns: int
    batch: SensorBatch | None = None
    converted: Converted | None = None
    stream_sequence: int | None = None
    """Cluster mode: the batch's sequence in the batch stream, stored as applied in the group's transaction
    (``server.cluster``)."""

    def __post_init__(self) -> None:
        if (self.batch is None) == (self.converted is None):
            raise ValueError("a submission carries either the batch or its conversion")

    @classmethod
    def of(cls, batch: SensorBatch, raw: bytes, received_ns: int) -> Submission:
        return cls(BatchHeader.of(batch), raw, received_ns, batch=batch)


@dataclass
class GroupResult:
    receipts: list[BatchReceipt | ProblemError]
    messages: list[LiveMessage] = field(default_factory=list)
