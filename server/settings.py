"""All configuration, from the environment (``CROWDSLAM_*``) or ``.env``. Nothing else reads os.environ."""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from schemas.sensors import MAX_BATCH_BYTES


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="CROWDSLAM_", env_file=".env", extra="ignore")

    data_dir: Path = Field(
        default=Path("crowdslam-data"),
        description="Where the embedded SQLite database, recordings and the numba cache live.",
    )
    database_url: str | None = Field(
        default=None,
        description="SQLAlchemy URL, e.g. postgresql+psycopg://user@host/db. Default: SQLite in data_dir.",
    )
    max_batch_bytes: int = Field(default=MAX_BATCH_BYTES, gt=0)
    max_request_bytes: int = Field(
        default=256 * 1024,
        gt=0,
        description="Largest body of any request but a batch; refused with 413 before it is read, before "
        "the key is checked.",
    )
    max_plan_bytes: int = Field(
        default=8 * 1024 * 1024,
        gt=0,
        description="Largest floor plan (GeoJSON) an operator may upload; 413 before it is read.",
    )
    device_rate_per_s: float = Field(
        default=20.0,
        ge=0.0,
        description="Batches a device key may post per second, after a burst of device_burst (429 with "
        "Retry-After beyond). 0 turns the limit off.",
    )
    device_burst: float = Field(
        default=120.0, ge=1.0, description="Batches a device key may post at once (two minutes' worth)."
    )
    max_live_sockets_per_key: int = Field(
        default=20, ge=1, description="Live WebSockets one key may hold open at once (4429 beyond)."
    )
    extent_margin_m: float = Field(
        default=1000.0,
        ge=0.0,
        le=100_000.0,
        description="How far beyond a building's floors (their width and height) a fix, tag or anchor may "
        "lie; one farther is refused with 422.",
    )
    cold_start: bool = Field(
        default=False,
        description="Place phones that post no fix by the crowd's WiFi fingerprint map (dynamicslam); their "
        "receipts say tracking once the estimate is confident.",
    )
    metrics_need_key: bool = Field(
        default=False,
        description="Serve /metrics only to a site-wide operator key (it names every building).",
    )
    seed: int = Field(default=0, description="Root seed of every filter's random stream.")
    encounter_calibration: Path | None = Field(
        default=None,
        description="JSON of the encounter range models (crowdslam calibrate). Default: the bundled fit from "
        "the simulated paper testbed; calibrate real buildings.",
    )
    record: bool = Field(default=True, description="Record every accepted batch and estimate to MCAP.")
    snapshot_period_s: float = Field(
        default=60.0,
        ge=0.0,
        description="How often each building's tracker is snapshotted to SQL. After a crash, the batches "
        "acknowledged since the snapshot are replayed from the batch log, so this bounds restart time.",
    )
    sqlite_checkpoint_period_s: float = Field(
        default=0.1,
        ge=0.0,
        description="SQLite only: how often a background thread copies the write-ahead log into the "
        "database file, so that the commit which checkpoints finds little left to copy "
        "(server/store/wal_checkpoints.py). 0 leaves it all to the commits' checkpoints.",
    )
    position_history_days: float = Field(
        default=2.0,
        ge=0.0,
        description="How long each user's position history is kept (GET .../users/{user}/positions, "
        "GET .../positions?at_ms=, the dashboard's history slider); older rows are pruned in the background. "
        "Every user's latest position is kept regardless. 0 keeps all.",
    )
    position_history_period_s: float = Field(
        default=2.0,
        ge=0.0,
        le=3600.0,
        description="A user's position history keeps one estimate in this period (its latest position is "
        "updated with every batch): the dashboard's history slider shows a point every 2 s. 0 keeps every "
        "estimate.",
    )
    batch_ids_hours: float = Field(
        default=1.0,
        ge=0.0,
        description="How long the ids of accepted batches are kept, so that a retry answers duplicate. A "
        "batch retried later answers late instead (its sequence number is not after its device's last): "
        "either way it is never applied twice. Batches a restart would replay are never pruned. 0 keeps all.",
    )
    recording_days: float = Field(
        default=7.0,
        ge=0.0,
        description="How long the MCAP recordings are kept: whole hourly files older than this are deleted, "
        "oldest first (replay and signal-map builds read what is left). 0 keeps all.",
    )
    recording_max_gb: float = Field(
        default=0.0,
        ge=0.0,
        description="The most the recordings of all buildings may take, in GB (10^9 bytes): past it the "
        "oldest hourly files are deleted first. 0: no cap but the days.",
    )
    min_free_disk_gb: float = Field(
        default=2.0,
        ge=0.0,
        description="Below this much free space on the data directory's disk, /healthz says degraded.",
    )
    user_idle_s: float = Field(
        default=900.0,
        ge=0.0,
        description="A user not heard from for this long is forgotten by its building's tracker at the next "
        "snapshot (its filter's memory freed); it needs a new position fix when it comes back. 0 keeps every "
        "user (memory then grows with every phone that ever posted).",
    )
    building_processes: bool | None = Field(
        default=None,
        description="Run each building in a process of its own (server/buildings/process.py): its batch path "
        "then has a core of its own beside the HTTP front's. Unset: on where this process may use more than "
        "one core, off on one core (where a building's process only adds its overhead).",
    )
    group_linger_ms: float = Field(
        default=20.0,
        ge=0.0,
        le=1000.0,
        description="While batches arrive faster than a building applies them one by one, its next group "
        "starts this long after the previous one started, so that the batches arriving meanwhile share its "
        "fixed cost (a transaction, the filters' calls). A phone posting alone never waits. 0: every "
        "group starts as soon as the building is free.",
    )
    key_cache_s: float = Field(
        default=30.0,
        ge=0.0,
        description="How long an authenticated key is remembered; a key revoked in the database stops "
        "working within this time. 0 checks the database on every request.",
    )
    mode: Literal["dynamicslam", "semanticslam"] = Field(
        default="dynamicslam", description="semanticslam turns human anchors (encounters) off."
    )
    encounter_wifi_model: Literal["wifi-eq3", "wifi-fingerprint"] = Field(
        default="wifi-eq3",
        description="WiFi encounter detector: the paper's Eq. 3, or our union-fingerprint model (its range "
        "model must be in the encounter calibration: crowdslam calibrate fits both).",
    )
    signal_map_modalities: list[Literal["wifi", "bluetooth", "magnetic", "lte"]] = Field(
        default=["wifi"],
        min_length=1,
        description="Signal kernels multiplied into a signal-map build's similarity (SignalSLAM Section "
        "II-D); a modality a window lacks is neutral. On msindoor site1 F1 WiFi alone was best.",
    )
    foxglove_port: int | None = Field(
        default=None,
        ge=0,
        le=65535,
        description="Also serve every building's live positions, anchors and encounters to the Foxglove app "
        "or Lichtblick (foxglove-sdk's WebSocket server) on this port; 0 picks a free one. Off by default.",
    )
    foxglove_host: str = Field(
        default="127.0.0.1", description="Where the Foxglove server listens (it has no authentication)."
    )
    fingerprint_fixes: bool = Field(
        default=True,
        description="In dynamicslam mode, also localise each WiFi scan on the fingerprint map the crowd "
        "learns while it is tracked and apply it as a robust position fix (on msindoor site1 F1, warm "
        "replay, seeds 0-3: p50 2.08-2.18 m with them, 2.16-2.25 m without).",
    )
    ws_compression: bool = Field(
        default=False,
        description="Per-message deflate on WebSockets. It compresses every live message once per "
        "dashboard; under load it was 7 % of the server's CPU with ten dashboards. Turn it on for "
        "dashboards on slow links.",
    )
    fastapi_telemetry: bool = Field(
        default=False,
        description="FastAPI's native OpenTelemetry: request spans, metrics and logs sent to the "
        "providers an OpenTelemetry SDK configures (FASTAPI_OTEL_AUTO_CONFIGURE=true adds OTLP "
        "exporters from the OTEL_* environment). Off, the server's own metrics are at /metrics; on, "
        "every request looks its providers up in the environment first.",
    )

    role: Literal["all", "front", "worker"] = Field(
        default="all",
        description="all: one process serves HTTP and tracks its buildings (the embedded default). front: "
        "a stateless HTTP/WebSocket front that publishes batches to NATS JetStream and answers with the "
        "receipts of the buildings' workers. worker: owns buildings through leases and tracks them. front "
        "and worker need nats_url and PostgreSQL.",
    )
    nats_url: str | None = Field(
        default=None,
        description="NATS server(s) of the cluster, e.g. nats://127.0.0.1:4222 (comma-separated for "
        "several), with JetStream enabled. Keep it private to the cluster: its messages are trusted.",
    )
    lease_ttl_s: float = Field(
        default=10.0,
        ge=1.0,
        le=300.0,
        description="Cluster: how long a worker's lease on a building lives without a refresh (refreshed "
        "every third of it). A killed worker's buildings are taken over within this time; every worker "
        "must use the same value.",
    )
    stream_retention_s: float = Field(
        default=3600.0,
        gt=0.0,
        description="Cluster: how long the batch stream keeps a batch. The stream is a transport, not the "
        "record (the batch log in SQL is): a batch is acknowledged only once its worker committed it, and "
        "one no worker applied within receipt_timeout_s was answered 503, so the phone sends it again.",
    )
    receipt_timeout_s: float = Field(
        default=15.0,
        gt=0.0,
        le=600.0,
        description="Cluster: how long a front waits for the worker's receipt of a batch or the answer to an "
        "operator's call before answering 503 with Retry-After (the retry is safe: a batch applied meanwhile "
        "answers duplicate).",
    )

    webhook_allowed_hosts: str = Field(
        default="",
        description="Host names and CIDRs (comma-separated) a webhook may reach although they are loopback, "
        "link-local, private or otherwise not public, e.g. receiver.internal,10.0.5.0/24. Every other such "
        "address is refused when the webhook is stored and at every delivery (checked on the resolved "
        "address).",
    )
    webhook_max_attempts: int = Field(
        default=8,
        ge=1,
        le=50,
        description="Tries of one webhook delivery before it gives up; the webhook is then suspended (its "
        "pending deliveries given up, no new ones) until an operator PUTs it again.",
    )
    webhook_retry_s: float = Field(
        default=2.0,
        gt=0.0,
        le=3600.0,
        description="A failed delivery is tried again after this long, doubled at each try (at most 10 "
        "minutes); with the defaults a receiver may be down about 8 minutes before the webhook is suspended.",
    )
    webhook_timeout_s: float = Field(
        default=5.0, gt=0.0, le=60.0, description="How long a webhook receiver has to answer a delivery."
    )
    tls_cert: Path | None = Field(
        default=None,
        description="PEM certificate (chain) to serve HTTPS with, beside tls_key (crowdslam serve "
        "--tls-cert). Phones give the phone page their motion sensors only over HTTPS.",
    )
    tls_key: Path | None = Field(default=None, description="The PEM private key of tls_cert.")

    @field_validator("database_url")
    @classmethod
    def _a_store_crowdslam_runs_on(cls, url: str | None) -> str | None:
        """SQLite or PostgreSQL: another store (MySQL, say) would fail later with a driver's traceback."""
        if url and url.split(":", 1)[0].split("+", 1)[0] not in ("sqlite", "postgresql"):
            raise ValueError(
                "crowdslam stores its data in SQLite (the default) or PostgreSQL: give a URL like "
                "postgresql+psycopg://user@host/db"
            )
        return url

    @property
    def max_ws_frame_bytes(self) -> int:
        """The largest WebSocket frame the server reads (uvicorn's ``ws_max_size``; its own default is
        16 MiB): a batch streamed on ``/stream``, with room for one just past ``max_batch_bytes`` to get its
        413. A larger frame closes the socket with 1009 before it is read whole."""
        return self.max_batch_bytes + 64 * 1024

    @property
    def recordings_dir(self) -> Path:
        return self.data_dir / "recordings"

    @property
    def resolved_building_processes(self) -> bool:
        if self.building_processes is not None:
            return self.building_processes
        return usable_cores() > 1

    def cluster_problem(self) -> str | None:
        """What keeps this process from its cluster role, if anything (None in the embedded role)."""
        if self.role == "all":
            return None
        if not self.nats_url:
            return f"CROWDSLAM_ROLE={self.role} needs CROWDSLAM_NATS_URL (the cluster's NATS with JetStream)"
        if not self.resolved_database_url.startswith("postgresql"):
            return (
                f"CROWDSLAM_ROLE={self.role} needs PostgreSQL, shared by every front and worker: set "
                "CROWDSLAM_DATABASE_URL=postgresql+psycopg://user@host/db (SQLite is one process's database)"
            )
        return None

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'crowdslam.sqlite3').resolve()}"


RETIRED = {
    "CROWDSLAM_BATCH_IDS_DAYS": "set CROWDSLAM_BATCH_IDS_HOURS instead (in hours; default 1)",
}
"""Variables a server no longer reads, with what replaced them."""


def retired_variables() -> list[str]:
    """What the environment sets that this version no longer reads, and what to set instead: a setting
    silently ignored would leave an operator believing it holds."""
    return [f"{name} is no longer read: {instead}" for name, instead in RETIRED.items() if name in os.environ]


def usable_cores() -> int:
    """The cores this process may run on (its affinity: a container's CPU set, ``taskset``), not the
    machine's."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    return Settings()


def settings_problem(error: ValidationError) -> str:
    """The settings' validation errors as one line, each named by its environment variable."""
    parts = []
    for e in error.errors(include_url=False):
        name = "CROWDSLAM_" + "_".join(str(p) for p in e.get("loc", ())).upper()
        value = e.get("input")
        got = f" (got {value!r})" if isinstance(value, (str, int, float)) else ""
        message = str(e.get("msg", "invalid")).removeprefix("Value error, ")
        parts.append(f"{name}: {message}{got}")
    return "configuration: " + "; ".join(parts)
