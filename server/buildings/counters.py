"""What a building's tracking counts (exported as Prometheus metrics by ``server.metrics``)."""

from __future__ import annotations

from dataclasses import dataclass


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
    replay_failures: int = 0
    """Logged batches that could not be applied again on load (each tracker call's error logged): the building
    came back without them. The live path applied them, so each is an error of the server's."""
    log_bodies_cleared: int = 0
    """Logged batch bodies cleared once a snapshot covered them."""
    pruned_positions: int = 0
    """Position history rows deleted past their retention."""
    pruned_visits: int = 0
    """Closed zone visits deleted with the position history of their time."""
    zone_events: int = 0
    """Entries, exits and dwells stored (``server.buildings.zones``)."""
    webhook_deliveries: int = 0
    """Deliveries of those events queued for the building's webhooks (``server.webhooks``)."""
    pruned_batches: int = 0
    """Batch id rows deleted past their retention."""
    reclaimed_pages: int = 0
    """SQLite pages handed back to the file system (``server.store.db.reclaim_free_pages``)."""
    fingerprint_fixes: int = 0
    """Scans located on the crowd's WiFi fingerprint map and applied as position fixes."""
    users_evicted: int = 0
    """Users forgotten by the tracker after ``Retention.user_idle_s`` without a batch."""
    restore_failures: int = 0
    """Snapshots refused on load (another format, other parameters): tracking restarted from the SQL map."""
    reloads: int = 0
    """Times the building was loaded again from SQL after a group's transaction failed."""
    recording_failures: int = 0
    """Groups whose batches and estimates could not be written to the recording (a full disk): they were
    acknowledged all the same (the batch log in SQL is the acknowledgement)."""
    pruned_recordings: int = 0
    """Hourly recording files deleted past ``CROWDSLAM_RECORDING_DAYS`` or over ``_MAX_GB``."""
    disk_full_refusals: int = 0
    """Groups of batches refused (503) because the database's disk was full; nothing of them was kept."""
    failed_batches: int = 0
    """Batches that could not be applied (each answered with its own error; nothing of them kept)."""
    last_failure_unix_s: float = 0.0
    """Wall time of the latest failed or unreplayed batch (``/healthz`` calls a building failing lately
    degraded)."""
