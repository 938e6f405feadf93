"""SQLAlchemy 2 models. Schema changes go through Alembic migrations only (a test checks they agree)."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import (
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Float,
    ForeignKey,
    ForeignKeyConstraint,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    func,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

# Deterministic constraint names so migrations agree on SQLite and PostgreSQL.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

# BigInteger primary keys autoincrement on PostgreSQL; SQLite only autoincrements INTEGER.
BigIntPk = BigInteger().with_variant(Integer(), "sqlite")


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class BuildingRow(Base):
    __tablename__ = "buildings"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    name: Mapped[str] = mapped_column(String(128))
    origin_lat_deg: Mapped[float | None] = mapped_column(Float)
    origin_lon_deg: Mapped[float | None] = mapped_column(Float)
    rotation_rad: Mapped[float] = mapped_column(Float, default=0.0)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())


class FloorRow(Base):
    __tablename__ = "floors"

    building_id: Mapped[str] = mapped_column(ForeignKey("buildings.id", ondelete="CASCADE"), primary_key=True)
    level: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64))
    elevation_m: Mapped[float | None] = mapped_column(Float)
    width_m: Mapped[float | None] = mapped_column(Float)
    height_m: Mapped[float | None] = mapped_column(Float)


class StreamPositionRow(Base):
    """The last sequence of the cluster's batch stream a building's worker applied, written in the same
    transaction as those batches: a worker that takes the building over reads the stream from the next one."""

    __tablename__ = "stream_positions"
    __table_args__ = (ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),)

    building_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    sequence: Mapped[int] = mapped_column(BigInteger)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


class FloorPlanRow(Base):
    """A floor's plan (``schemas.floor_plans.FloorPlan``) as GeoJSON text in the building's local frame."""

    __tablename__ = "floor_plans"
    __table_args__ = (
        ForeignKeyConstraint(
            ["building_id", "level"], ["floors.building_id", "floors.level"], ondelete="CASCADE"
        ),
    )

    building_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    level: Mapped[int] = mapped_column(Integer, primary_key=True)
    geojson: Mapped[str] = mapped_column(Text)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


class DeviceRow(Base):
    __tablename__ = "devices"

    building_id: Mapped[str] = mapped_column(ForeignKey("buildings.id", ondelete="CASCADE"), primary_key=True)
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    user_id: Mapped[str] = mapped_column(String(64))
    ble_advertised_id: Mapped[str | None] = mapped_column(String(64))
    last_seq: Mapped[int | None] = mapped_column(BigInteger)
    install_ms: Mapped[int | None] = mapped_column(BigInteger)
    """The install ``last_seq`` counts in (``SensorBatch.install_ms``)."""
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())


class ApiKeyRow(Base):
    """Keys are stored as SHA-256 of the secret; only the short prefix is kept in clear to find them."""

    __tablename__ = "api_keys"
    __table_args__ = (
        CheckConstraint("scope IN ('operator', 'device', 'dashboard')", name="scope"),
        CheckConstraint(
            "scope != 'device' OR (device_id IS NOT NULL AND building_id IS NOT NULL)", name="device"
        ),
    )

    id: Mapped[int] = mapped_column(BigIntPk, primary_key=True, autoincrement=True)
    prefix: Mapped[str] = mapped_column(String(16), index=True)
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    scope: Mapped[str] = mapped_column(String(16))
    building_id: Mapped[str | None] = mapped_column(ForeignKey("buildings.id", ondelete="CASCADE"))
    device_id: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    last_used_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    """Written in bulk when the key cache is revalidated (``server.auth.KeyCache``), not on every request."""


class BatchRow(Base):
    """An accepted batch's id, kept ``CROWDSLAM_BATCH_IDS_HOURS`` to answer a retry ``duplicate``. The unique
    constraint on (building, device, batch id) is what detects retries. Its body, while a restart may need
    it, is in ``batch_log``: a row that stays is small, and the log's rows leave whole."""

    __tablename__ = "batches"
    __table_args__ = (
        ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),
        UniqueConstraint("building_id", "device_id", "batch_id", name="uq_batches_device_batch"),
        Index("ix_batches_building_received", "building_id", "received_at"),
    )

    id: Mapped[int] = mapped_column(BigIntPk, primary_key=True, autoincrement=True)
    building_id: Mapped[str] = mapped_column(String(64))
    device_id: Mapped[str] = mapped_column(String(64))
    batch_id: Mapped[str] = mapped_column(String(64))
    seq: Mapped[int] = mapped_column(BigInteger)
    t_first_ms: Mapped[int | None] = mapped_column(BigInteger)
    t_last_ms: Mapped[int | None] = mapped_column(BigInteger)
    n_bytes: Mapped[int] = mapped_column(Integer)
    applied: Mapped[bool] = mapped_column(Boolean, default=False)
    tracker_call: Mapped[int | None] = mapped_column(BigInteger)
    """The building's tracker call that applied it: a restart replays the log in the same groups."""
    received_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())


class BatchLogRow(Base):
    """The write-ahead log: an applied batch's body as posted (a zstd frame, ``server.store.batches``), from
    the transaction that acknowledges it until a tracker snapshot covers it (then the row is deleted). With
    the snapshot it restores tracking after a crash."""

    __tablename__ = "batch_log"
    __table_args__ = (
        ForeignKeyConstraint(["batch_row_id"], ["batches.id"], ondelete="CASCADE"),
        ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),
        Index("ix_batch_log_building_call", "building_id", "tracker_call"),
    )

    batch_row_id: Mapped[int] = mapped_column(BigIntPk, primary_key=True, autoincrement=False)
    building_id: Mapped[str] = mapped_column(String(64))
    tracker_call: Mapped[int] = mapped_column(BigInteger)
    body: Mapped[bytes] = mapped_column(LargeBinary)


class AnchorRow(Base):
    """A building anchor of the shared crowd map (mean, covariance, type, count, last seen)."""

    __tablename__ = "anchors"
    __table_args__ = (
        ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),
        Index("ix_anchors_building_floor", "building_id", "floor"),
        UniqueConstraint("building_id", "public_id", name="uq_anchors_public_id"),
    )

    id: Mapped[int] = mapped_column(BigIntPk, primary_key=True, autoincrement=True)
    building_id: Mapped[str] = mapped_column(String(64))
    public_id: Mapped[str] = mapped_column(String(64))
    floor: Mapped[int] = mapped_column(Integer, default=0)
    type: Mapped[str] = mapped_column(String(32))
    x_m: Mapped[float] = mapped_column(Float)
    y_m: Mapped[float] = mapped_column(Float)
    cov_xx: Mapped[float] = mapped_column(Float)
    cov_xy: Mapped[float] = mapped_column(Float)
    cov_yy: Mapped[float] = mapped_column(Float)
    observation_count: Mapped[int] = mapped_column(Integer, default=0)
    known: Mapped[bool] = mapped_column(Boolean, default=False)
    label: Mapped[str | None] = mapped_column(String(128))
    signature: Mapped[bytes | None] = mapped_column(LargeBinary)
    last_seen_ms: Mapped[int | None] = mapped_column(BigInteger)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())


class _EstimateColumns:
    """A user's estimate as both the position history and the latest positions store it."""

    device_id: Mapped[str] = mapped_column(String(64))
    t_ms: Mapped[int] = mapped_column(BigInteger)
    x_m: Mapped[float] = mapped_column(Float)
    y_m: Mapped[float] = mapped_column(Float)
    cov_xx: Mapped[float] = mapped_column(Float)
    cov_xy: Mapped[float] = mapped_column(Float)
    cov_yy: Mapped[float] = mapped_column(Float)
    heading_rad: Mapped[float] = mapped_column(Float)
    floor: Mapped[int] = mapped_column(Integer, default=0)
    floor_probability: Mapped[float] = mapped_column(Float, server_default=text("1.0"))
    source: Mapped[str] = mapped_column(String(16))


class PositionSnapshotRow(_EstimateColumns, Base):
    """Position history: one row per published estimate."""

    __tablename__ = "position_snapshots"
    __table_args__ = (
        ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),
        Index("ix_position_snapshots_user_time", "building_id", "user_id", "t_ms"),
        Index("ix_position_snapshots_building_stored", "building_id", "stored_at_ms"),
    )

    id: Mapped[int] = mapped_column(BigIntPk, primary_key=True, autoincrement=True)
    building_id: Mapped[str] = mapped_column(String(64))
    user_id: Mapped[str] = mapped_column(String(64))
    stored_at_ms: Mapped[int | None] = mapped_column(BigInteger)
    """Server time of the write: history is pruned by it (``t_ms`` is the phone's, and a replayed recording
    may be years old)."""


class LatestPositionRow(_EstimateColumns, Base):
    """Each user's latest position snapshot (GET /positions reads it; the history would need a scan)."""

    __tablename__ = "latest_positions"
    __table_args__ = (ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),)

    building_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    user_id: Mapped[str] = mapped_column(String(64), primary_key=True)


class TrackerSnapshotRow(Base):
    """The latest serialised tracker of one building (every user's filter, the crowd map, the encounter
    detector). With the batch bodies logged since, it restores tracking after a crash."""

    __tablename__ = "tracker_snapshots"
    __table_args__ = (ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),)

    building_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    format_version: Mapped[int] = mapped_column(Integer)
    tracker_call: Mapped[int] = mapped_column(BigInteger)
    state: Mapped[bytes] = mapped_column(LargeBinary)
    taken_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())


class ZoneRow(Base):
    """A zone an operator drew (``schemas.zones.ZoneIn``): its outline as a JSON list of [x, y] in the local
    frame, the ring not closed."""

    __tablename__ = "zones"
    __table_args__ = (ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),)

    building_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    floor: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(128))
    ring: Mapped[str] = mapped_column(Text)
    dwell_s: Mapped[float | None] = mapped_column(Float)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


class ZoneVisitRow(Base):
    """One user's stay in a zone: written by the batch that entered it, closed by the one that left it, in
    their transactions (``left_ms`` null: inside still). Occupancy at any time, and the zone's events, are
    read from these rows."""

    __tablename__ = "zone_visits"
    __table_args__ = (
        ForeignKeyConstraint(
            ["building_id", "zone_id"], ["zones.building_id", "zones.id"], ondelete="CASCADE"
        ),
        Index("ix_zone_visits_zone_entered", "building_id", "zone_id", "entered_ms"),
        Index("ix_zone_visits_user", "building_id", "user_id", "zone_id"),
        Index("ix_zone_visits_building_stored", "building_id", "stored_at_ms"),
    )

    id: Mapped[int] = mapped_column(BigIntPk, primary_key=True, autoincrement=True)
    building_id: Mapped[str] = mapped_column(String(64))
    zone_id: Mapped[str] = mapped_column(String(64))
    user_id: Mapped[str] = mapped_column(String(64))
    entered_ms: Mapped[int] = mapped_column(BigInteger)
    entered_probability: Mapped[float] = mapped_column(Float)
    left_ms: Mapped[int | None] = mapped_column(BigInteger)
    left_probability: Mapped[float | None] = mapped_column(Float)
    dwelled_ms: Mapped[int | None] = mapped_column(BigInteger)
    stored_at_ms: Mapped[int] = mapped_column(BigInteger)
    """Server time of the entry's write: visits are pruned by it, with the position history."""


class WebhookRow(Base):
    """Where a building's zone events are POSTed (``schemas.zones.WebhookIn``); its secret signs them."""

    __tablename__ = "webhooks"
    __table_args__ = (ForeignKeyConstraint(["building_id"], ["buildings.id"], ondelete="CASCADE"),)

    building_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    url: Mapped[str] = mapped_column(Text)
    secret: Mapped[str] = mapped_column(String(256))
    events: Mapped[str] = mapped_column(String(64))
    """The events it takes, comma-separated (``zone.enter,zone.exit``)."""
    suspended_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    """When a delivery gave up: no new events until the webhook is PUT again."""
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


class WebhookDeliveryRow(Base):
    """One event for one webhook: written in the transaction of the batch that caused it (an outbox), sent
    after, in order per webhook, and kept as its delivery log."""

    __tablename__ = "webhook_deliveries"
    __table_args__ = (
        ForeignKeyConstraint(
            ["building_id", "webhook_id"], ["webhooks.building_id", "webhooks.id"], ondelete="CASCADE"
        ),
        Index("ix_webhook_deliveries_hook", "building_id", "webhook_id", "id"),
        Index("ix_webhook_deliveries_due", "status", "next_attempt_ms"),
    )

    id: Mapped[int] = mapped_column(BigIntPk, primary_key=True, autoincrement=True)
    building_id: Mapped[str] = mapped_column(String(64))
    webhook_id: Mapped[str] = mapped_column(String(64))
    event: Mapped[str] = mapped_column(String(16))
    body: Mapped[str] = mapped_column(Text)
    created_ms: Mapped[int] = mapped_column(BigInteger)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    status: Mapped[str] = mapped_column(String(16))
    """pending, delivered or gave_up."""
    next_attempt_ms: Mapped[int | None] = mapped_column(BigInteger)
    claimed_until_ms: Mapped[int | None] = mapped_column(BigInteger)
    """A dispatcher sending it holds it until then (another process's may take it after)."""
    http_status: Mapped[int | None] = mapped_column(Integer)
    error: Mapped[str | None] = mapped_column(Text)
    delivered_ms: Mapped[int | None] = mapped_column(BigInteger)
