"""A batch as it goes to its building (its header, its columns and its landmarks), as it crosses to a
building's process or a cluster's worker (``batch_fields`` and ``received_batch``), and what a group of
batches gives back."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

from pydantic import TypeAdapter

from schemas.api import BatchReceipt
from schemas.live import LiveMessage
from schemas.sensors import Landmark, SensorBatch
from server.errors import InvalidInputError, ProblemError
from server.ingestion import convert, transport
from server.ingestion.decoding import decode_batch


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


@dataclass(frozen=True, slots=True)
class Submission:
    """One accepted batch for its building, in the one shape every mode gives it (threads, processes, a
    cluster): its sensors as the columns the front packed (``server.ingestion.convert.packed``) and its
    landmarks, which only the building can place (``convert.placed``)."""

    header: BatchHeader
    raw: bytes  # the body as posted, for the batch log and the recording
    received_ns: int
    columns: transport.PackedBatch
    landmarks: tuple[Landmark, ...] = ()
    stream_sequence: int | None = None
    """Cluster mode: the batch's sequence in the batch stream, stored as applied in the group's transaction
    (``server.cluster``)."""

    @classmethod
    def of(cls, batch: SensorBatch, raw: bytes, received_ns: int) -> Submission:
        """The front's conversion of a validated batch. Raises ``InvalidInputError`` for values its arrays
        refuse."""
        try:
            columns = convert.packed(batch)
        except ValueError as exc:
            raise InvalidInputError(str(exc)) from None
        return cls(BatchHeader.of(batch), raw, received_ns, columns, tuple(batch.landmarks))


@dataclass
class GroupResult:
    receipts: list[BatchReceipt | ProblemError]
    messages: list[LiveMessage] = field(default_factory=list)

    def wire_receipts(self) -> list[bytes | ProblemError]:
        """The receipts as the batches' answers: each a receipt's JSON, or the error that refused it."""
        return [r if isinstance(r, ProblemError) else r.model_dump_json().encode() for r in self.receipts]


BatchFields = tuple[bytes, int, tuple[Any, ...], tuple[Any, ...] | None, bytes | None]
"""A batch on the socket: raw body, received_ns, its ``BatchHeader``, its columns and its landmarks' JSON
(None: none), the header and the columns as plain tuples (a named tuple pickles by its class, which costs
both sides of every batch)."""

_LANDMARKS = TypeAdapter(list[Landmark])


def batch_fields(submission: Submission) -> BatchFields:
    """A batch as it crosses to its building's process or a cluster's worker."""
    landmarks = _LANDMARKS.dump_json(list(submission.landmarks)) if submission.landmarks else None
    header = tuple(submission.header)
    return submission.raw, submission.received_ns, header, tuple(submission.columns), landmarks


def received_batch(
    raw: bytes,
    received_ns: int,
    header: tuple[Any, ...],
    columns: tuple[Any, ...] | None,
    landmarks: bytes | None = None,
) -> Submission:
    """The building's side of ``batch_fields``. A batch without columns (a cluster's stream may still hold
    one an earlier front published) is converted here as a front would."""
    if columns is None:
        return Submission.of(decode_batch(raw, max(len(raw), 1)), raw, received_ns)
    return Submission(
        BatchHeader._make(header),
        raw,
        received_ns,
        transport.PackedBatch._make(columns),
        () if landmarks is None else tuple(_LANDMARKS.validate_json(landmarks)),
    )


def transportable(exc: Exception) -> Exception:
    """The error as the front will raise it: a ProblemError as it is, anything else as a RuntimeError
    naming it (the front answers 500 and logs it, as for an error in its own process)."""
    if isinstance(exc, ProblemError):
        return exc
    return RuntimeError(f"{type(exc).__name__} in the building's process: {exc}")
