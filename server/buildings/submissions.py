"""A batch as it goes to its building (its header, the validated or converted batch), as it crosses to a
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
from server.ingestion.convert import Converted
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
    landmarks: list[Landmark] | None = None
    """The landmarks of a batch the front converted without them: its building places them
    (``server.ingestion.convert.with_landmarks``), as only it knows its frame, extent, floors and anchors."""

    def __post_init__(self) -> None:
        if (self.batch is None) == (self.converted is None):
            raise ValueError("a submission carries either the batch or its conversion")
        if self.landmarks is not None and self.converted is None:
            raise ValueError("landmarks travel apart only with a converted batch")

    @classmethod
    def of(cls, batch: SensorBatch, raw: bytes, received_ns: int) -> Submission:
        return cls(BatchHeader.of(batch), raw, received_ns, batch=batch)


@dataclass
class GroupResult:
    receipts: list[BatchReceipt | ProblemError]
    messages: list[LiveMessage] = field(default_factory=list)

    def wire_receipts(self) -> list[bytes | ProblemError]:
        """The receipts as the batches' answers: each a receipt's JSON, or the error that refused it."""
        return [r if isinstance(r, ProblemError) else r.model_dump_json().encode() for r in self.receipts]


BatchFields = tuple[bytes, int, tuple[Any, ...], tuple[Any, ...] | None, bytes | None]
"""A batch on the socket: raw body, received_ns, its ``BatchHeader``, its packed conversion (None: the
building decodes the raw body) and the JSON of the landmarks that conversion left for the building to place
(None: none), the header and the conversion as plain tuples (a named tuple pickles by its class, which costs
both sides of every batch)."""

_LANDMARKS = TypeAdapter(list[Landmark])


def batch_fields(submission: Submission) -> BatchFields:
    """The front's side: a batch as it crosses to its building, converted as far as that needs nothing of
    the building: a batch with landmarks (a phone's first, with its fix) is packed without them, and its
    landmarks travel as their JSON for the building to place. Raises ``InvalidInputError`` where the
    building's conversion would have answered it."""
    packed = None
    landmarks = None
    batch = submission.batch
    if batch is not None:
        try:
            packed = convert.packed_without_context(batch, landmarks_apart=True)  # straight to the bytes
            if packed is None:  # raw IMU, a barometer: the arrays, packed
                converted = convert.without_context(batch, landmarks_apart=True)
                packed = None if converted is None else transport.pack(converted.user_batch)
        except ValueError as exc:
            raise InvalidInputError(str(exc)) from None
        if batch.landmarks:
            landmarks = _LANDMARKS.dump_json(batch.landmarks)
    fields = None if packed is None else tuple(packed)
    return submission.raw, submission.received_ns, tuple(submission.header), fields, landmarks


def received_batch(
    raw: bytes,
    received_ns: int,
    header: tuple[Any, ...],
    packed: tuple[Any, ...] | None,
    landmarks: bytes | None = None,
) -> Submission:
    """The building's side of ``batch_fields`` (also of an earlier front's batch, without ``landmarks``)."""
    if packed is None:
        batch = decode_batch(raw, max(len(raw), 1))  # validated by the front already
        return Submission(BatchHeader._make(header), raw, received_ns, batch=batch)
    user_batch = transport.unpack(transport.PackedBatch._make(packed))
    return Submission(
        BatchHeader._make(header),
        raw,
        received_ns,
        converted=convert.Converted(user_batch, []),
        landmarks=None if landmarks is None else _LANDMARKS.validate_json(landmarks),
    )


def transportable(exc: Exception) -> Exception:
    """The error as the front will raise it: a ProblemError as it is, anything else as a RuntimeError
    naming it (the front answers 500 and logs it, as for an error in its own process)."""
    if isinstance(exc, ProblemError):
        return exc
    return RuntimeError(f"{type(exc).__name__} in the building's process: {exc}")
