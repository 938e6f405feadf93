"""What a building's tracking counts, keeps and is given: its counters (exported as Prometheus metrics), its
configuration and retention of history, one submitted batch, and a group's result."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

from schemas.api import BatchReceipt
from schemas.live import LiveMessage
from schemas.sensors import SensorBatch
from server.errors import ProblemError
from server.ingestion.convert import Converted
from slam_core.encounters.models import Calibration
from slam_core.tracking.tracker import TrackerParams


@dataclass
class Counters:
    batches: int = 0
    duplicates: int = 0
    late: int = 0
    estimates: int = 0
    encounters: int = 0
    """Detections chosen as human anchors (``slam_core.encounters.selection``), applied or gated."""
    encounters_applied: int = 0
    encounter_detections: int = 0
    """Every WiFi or Bluetooth encounter detection, chosen or not."""
    steps_dropped: int = 0
    steps_detected: int = 0
    """Steps the PDR front-end found in raw IMU."""
    imu_samples_dropped: int = 0
    """IMU samples older than what a user's front-end had consumed (late or re-sent batches)."""
    recentred: int = 0
    snapshots: int = 0
    snapshot_failures: int = 0
    """Periodic snapshots that could not be compressed (the batch log keeps what they would have covered)."""
    replayed: int = 0
    """Logged batches re-applied on load, after a crash."""
    log_bodies_cleared: int = 0
    """Logged batch bodies cleared once a snapshot covered them."""
    pruned_positions: int = 0
    """Position history rows deleted past their retention."""
    pruned_batches: int = 0
    """Batch id rows deleted past their retention."""
    fingerprint_fixes: int = 0
    """Scans located on the crowd's WiFi fingerprint map and applied as position fixes."""
    users_evicted: int = 0
    """Users forgotten by the tracker after ``Retention.user_idle_s`` without a batch."""
    restore_failures: int = 0
    """Snapshots refused on load (another format, other parameters): tracking restarted from the SQL map."""


@dataclass(frozen=True)
class Retention:
    """How much history SQL keeps (``Settings.position_history_days``, ``batch_ids_days``; None: all)."""

    position_history_days: float | None = 7.0
    batch_ids_days: float | None = 2.0
    prune_period_s: float = 1.0
    """Old rows are deleted at most this often, ``prune_chunk`` per table at a time: a building inserting
    3,000 position rows a second keeps up, and no group waits behind a long delete."""
    prune_chunk: int = 10_000
    log_clear_per_batch: float = 2.0
    """Each group clears this many logged batch bodies per batch it holds, of those a snapshot covers: the
    clearing outpaces the logging, and costs each group in proportion to its size (~7 us a row on SQLite
    here, measured apart on 2026-12-04), where clearing a minute's log at once had held one group for
    ~0.6 s at 1,000 phones."""
    user_idle_s: float | None = 900.0
    """A user not heard from for this long is forgotten by the tracker (its slot, particles and maps freed;
    it needs a new fix when it comes back), at the next snapshot, so a restart's replay never spans an
    eviction. None keeps every user."""


@dataclass(frozen=True)
class TrackingConfig:
    """How every building of a server is tracked: the engine, its seed, snapshots and retention."""

    params: TrackerParams
    calibration: Calibration
    seed: int = 0
    snapshot_period_s: float = 60.0
    retention: Retention = field(default_factory=Retention)


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

    @classmethod
    def of(cls, batch: SensorBatch) -> BatchHeader:
        return cls(
            batch.device_id,
            batch.effective_user_id,
            batch.batch_id,
            batch.seq,
            batch.ble_advertised_id,
            batch.time_span_ms(),
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
