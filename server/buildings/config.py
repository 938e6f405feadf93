"""How a server tracks its buildings: the engine, its seed, snapshots, and how much history SQL keeps."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from slam_core.encounters.models import Calibration
from slam_core.tracking.tracker import TrackerParams


@dataclass(frozen=True)
class Retention:
    """How much history SQL and the recordings keep (``Settings.position_history_days``, ``batch_ids_hours``,
    ``recording_days``, ``recording_max_gb``; None: all)."""

    position_history_days: float | None = 2.0
    position_history_period_s: float = 2.0
    """A user's history keeps one estimate in this period; 0 keeps every one."""
    batch_ids_hours: float | None = 1.0
    recording_days: float | None = 7.0
    recording_max_bytes: int | None = None
    prune_period_s: float = 1.0
    """Old rows are deleted at most this often, ``prune_chunk`` per table at a time: a building inserting
    3,000 position rows a second keeps up, and no group waits behind a long delete."""
    prune_chunk: int = 10_000
    log_clear_per_batch: float = 2.0
    """Each group clears this many logged batch bodies per batch it holds, of those a snapshot covers: the
    clearing outpaces the logging and costs each group in proportion to its size, where clearing a minute's
    log at once would hold one group far longer than any other."""
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
    signal_maps_dir: Path | None = None
    """Where signal-map builds are written: a building's tracker loads its latest build's radio map."""
    extent_margin_m: float = 1000.0
    """How far beyond its floors a position posted to a building may lie (``server.ingestion.extent``)."""
    group_linger_s: float = 0.02
    """How long a busy building lets batches gather into its next group (``server.buildings.groups.
    GroupPacing``): each group pays a fixed cost (a transaction, the filters' calls), which batches
    gathered into one group share."""
