"""All SQL of the server, one function per question. Services call these; they never commit (the caller
owns the transaction)."""

from __future__ import annotations

import hashlib
from collections.abc import Collection, Mapping, Sequence
from datetime import UTC, datetime
from typing import Any, cast

from sqlalchemy import (
    ColumnElement,
    CursorResult,
    Table,
    bindparam,
    delete,
    exists,
    func,
    insert,
    select,
    update,
)
from sqlalchemy.orm import Session

from server.store.db import execute_many, insert_once, upsert
from server.store.models import (
    AnchorRow,
    ApiKeyRow,
    BatchLogRow,
    BatchRow,
    BuildingRow,
    DeviceRow,
    FloorPlanRow,
    FloorRow,
    LatestPositionRow,
    PositionSnapshotRow,
    StreamPositionRow,
    TrackerSnapshotRow,
    WebhookDeliveryRow,
    WebhookRow,
    ZoneRow,
    ZoneVisitRow,
)

# ----------------------------------------------------------------------------- buildings


def get_building(session: Session, building_id: str) -> BuildingRow | None:
    return session.get(BuildingRow, building_id)


def list_buildings(session: Session, ids: Sequence[str] | None = None) -> list[BuildingRow]:
    stmt = select(BuildingRow).order_by(BuildingRow.id)
    if ids is not None:
        stmt = stmt.where(BuildingRow.id.in_(list(ids)))
    return list(session.execute(stmt).scalars())


def insert_building(session: Session, row: BuildingRow, floors: Sequence[FloorRow]) -> bool:
    """Insert a building and its floors; False when the id is taken (decided by the primary key)."""
    values = {
        "id": row.id,
        "name": row.name,
        "origin_lat_deg": row.origin_lat_deg,
        "origin_lon_deg": row.origin_lon_deg,
        "rotation_rad": row.rotation_rad,
    }
    inserted = insert_once(session, BuildingRow, values, ["id"], BuildingRow.id)
    if inserted is None:
        return False
    for floor in floors:
        floor.building_id = row.id
        session.add(floor)
    session.flush()
    return True


def list_floors(session: Session, building_id: str) -> list[FloorRow]:
    stmt = select(FloorRow).where(FloorRow.building_id == building_id).order_by(FloorRow.level)
    return list(session.execute(stmt).scalars())


def floor_plan(session: Session, building_id: str, level: int) -> str | None:
    """The floor's plan as local-frame GeoJSON text, or None."""
    row = session.get(FloorPlanRow, (building_id, level))
    return None if row is None else row.geojson


class StaleStreamPositionError(RuntimeError):
    """A batch at or before the building's stored stream position: applying it would apply it twice or out of
    order (a worker that lost its lease, or a redelivery)."""

    def __init__(self, building_id: str, stored: int, sequence: int) -> None:
        super().__init__(
            f"building {building_id!r} has applied the batch stream up to {stored}; {sequence} is not after"
        )
        self.stored = stored


def stream_position(session: Session, building_id: str) -> int:
    """The last batch-stream sequence applied to the building (0: none yet)."""
    row = session.get(StreamPositionRow, building_id)
    return 0 if row is None else int(row.sequence)


def advance_stream_position(session: Session, building_id: str, sequence: int) -> None:
    """Record ``sequence`` as applied, in the caller's transaction; ``StaleStreamPositionError`` unless it is
    after the stored one (the transaction is then to be rolled back: its batches were applied before)."""
    now = datetime.now(UTC)
    table = cast("Table", StreamPositionRow.__table__)
    # a Core statement on the session's connection: once a group, and the ORM's session synchronisation
    # has nothing to do for it
    moved = cast(
        "CursorResult[Any]",
        session.connection().execute(
            update(table)
            .where(table.c.building_id == building_id, table.c.sequence < sequence)
            .values(sequence=sequence, updated_at=now)
        ),
    )
    if moved.rowcount:
        return
    stored = session.get(StreamPositionRow, building_id)
    if stored is not None:
        raise StaleStreamPositionError(building_id, int(stored.sequence), sequence)
    # the first batch: a concurrent first insert by another worker fails on the primary key
    session.add(StreamPositionRow(building_id=building_id, sequence=sequence, updated_at=now))
    session.flush()


def floor_plan_levels(session: Session, building_id: str) -> list[int]:
    """The levels of the building's floors that have a plan."""
    stmt = (
        select(FloorPlanRow.level).where(FloorPlanRow.building_id == building_id).order_by(FloorPlanRow.level)
    )
    return [int(level) for level in session.execute(stmt).scalars()]


def save_floor_plan(session: Session, building_id: str, level: int, geojson: str) -> None:
    """Insert or replace the floor's plan (the floor must exist)."""
    values = {"building_id": building_id, "level": level, "geojson": geojson, "updated_at": datetime.now(UTC)}
    upsert(session, FloorPlanRow, [values], ["building_id", "level"])


# ----------------------------------------------------------------------------- zones


def list_zones(session: Session, building_id: str) -> list[ZoneRow]:
    stmt = select(ZoneRow).where(ZoneRow.building_id == building_id).order_by(ZoneRow.id)
    return list(session.execute(stmt).scalars())


def get_zone(session: Session, building_id: str, zone_id: str) -> ZoneRow | None:
    return session.get(ZoneRow, (building_id, zone_id))


def save_zone(session: Session, row: dict[str, Any]) -> None:
    """Insert or replace a zone (its visits stay)."""
    upsert(session, ZoneRow, [{**row, "updated_at": datetime.now(UTC)}], ["building_id", "id"])


def delete_zone(session: Session, building_id: str, zone_id: str) -> bool:
    """Delete a zone and its visits; whether it existed."""
    session.execute(
        delete(ZoneVisitRow).where(ZoneVisitRow.building_id == building_id, ZoneVisitRow.zone_id == zone_id)
    )
    result = session.execute(delete(ZoneRow).where(ZoneRow.building_id == building_id, ZoneRow.id == zone_id))
    return bool(cast(CursorResult[Any], result).rowcount)


_OPEN_VISIT = (
    (ZoneVisitRow.building_id == bindparam("b"))
    & (ZoneVisitRow.zone_id == bindparam("z"))
    & (ZoneVisitRow.user_id == bindparam("u"))
    & ZoneVisitRow.left_ms.is_(None)
)
_ENTER = insert(ZoneVisitRow)
_EXIT = (
    update(ZoneVisitRow).where(_OPEN_VISIT).values(left_ms=bindparam("t"), left_probability=bindparam("p"))
)
_DWELL = update(ZoneVisitRow).where(_OPEN_VISIT).values(dwelled_ms=bindparam("t"))


def record_zone_events(
    session: Session, building_id: str, events: Sequence[tuple[str, str, str, int, float]], stored_at_ms: int
) -> None:
    """Apply one tracker call's zone events ``(user, zone, kind, t_ms, probability)`` to the visits: an
    entry opens one, an exit closes the user's open visit of the zone, a dwell marks it. A call tells a user
    at most one entry or exit of a zone (and a dwell after its entry), so the entries go first, then the
    exits, then the dwells, each kind in one statement."""
    enters = [
        {
            "building_id": building_id,
            "zone_id": zone,
            "user_id": user,
            "entered_ms": t_ms,
            "entered_probability": p,
            "stored_at_ms": stored_at_ms,
        }
        for user, zone, kind, t_ms, p in events
        if kind == "enter"
    ]
    execute_many(session, _ENTER, enters)
    exits = [{"b": building_id, "z": z, "u": u, "t": t, "p": p} for u, z, k, t, p in events if k == "exit"]
    execute_many(session, _EXIT, exits)
    dwells = [{"b": building_id, "z": z, "u": u, "t": t} for u, z, k, t, _ in events if k == "dwell"]
    execute_many(session, _DWELL, dwells)


def open_visits(
    session: Session, building_id: str, users: Collection[str] | None = None
) -> list[ZoneVisitRow]:
    """The visits still open (of ``users``, or of everyone), in the order they were entered."""
    stmt = select(ZoneVisitRow).where(ZoneVisitRow.building_id == building_id, ZoneVisitRow.left_ms.is_(None))
    if users is not None:
        stmt = stmt.where(ZoneVisitRow.user_id.in_(list(users)))
    return list(session.execute(stmt.order_by(ZoneVisitRow.id)).scalars())


def close_lost_visits(
    session: Session, building_id: str, users: Collection[str] | None = None
) -> list[tuple[str, str, int]]:
    """Close the open visits (of ``users``, or of everyone) the tracker no longer follows (the user was
    forgotten idle, or the building's filters started anew): left where the user was last seen (its latest
    position's time, not before the entry), with probability 0. Returns each as (user, zone, left_ms)."""
    visits = open_visits(session, building_id, users)
    whose = {v.user_id for v in visits}
    last = {r.user_id: r.t_ms for r in latest_positions_of(session, building_id, whose)}
    closed = []
    for v in visits:
        left_ms = max(v.entered_ms, last.get(v.user_id, v.entered_ms))
        session.execute(
            update(ZoneVisitRow)
            .where(ZoneVisitRow.id == v.id, ZoneVisitRow.left_ms.is_(None))
            .values(left_ms=left_ms, left_probability=0.0)
        )
        closed.append((v.user_id, v.zone_id, left_ms))
    return closed


def zone_occupancy(session: Session, building_id: str, at_ms: int | None = None) -> dict[str, int]:
    """Users inside each zone now (``at_ms`` None: the open visits) or at ``at_ms`` (entered by then and not
    yet left); zones with nobody are left out."""
    inside: ColumnElement[bool] = ZoneVisitRow.left_ms.is_(None)
    if at_ms is not None:
        inside = (ZoneVisitRow.entered_ms <= at_ms) & (inside | (ZoneVisitRow.left_ms > at_ms))
    stmt = (
        select(ZoneVisitRow.zone_id, func.count(func.distinct(ZoneVisitRow.user_id)))
        .where(ZoneVisitRow.building_id == building_id, inside)
        .group_by(ZoneVisitRow.zone_id)
    )
    return {str(zone): int(n) for zone, n in session.execute(stmt)}


def zone_visits(
    session: Session, building_id: str, zone_id: str, since_ms: int, until_ms: int, limit: int
) -> list[ZoneVisitRow]:
    """The zone's visits that overlap [since_ms, until_ms), in the order they were entered (at most
    ``limit``)."""
    stmt = (
        select(ZoneVisitRow)
        .where(
            ZoneVisitRow.building_id == building_id,
            ZoneVisitRow.zone_id == zone_id,
            ZoneVisitRow.entered_ms < until_ms,
            ZoneVisitRow.left_ms.is_(None) | (ZoneVisitRow.left_ms >= since_ms),
        )
        .order_by(ZoneVisitRow.entered_ms, ZoneVisitRow.id)
        .limit(limit)
    )
    return list(session.execute(stmt).scalars())


def delete_user_visits(session: Session, building_id: str, user_id: str) -> int:
    """Delete a user's visits (a person asked to be forgotten); how many went."""
    result = session.execute(
        delete(ZoneVisitRow).where(ZoneVisitRow.building_id == building_id, ZoneVisitRow.user_id == user_id)
    )
    return int(cast(CursorResult[Any], result).rowcount or 0)


# ----------------------------------------------------------------------------- webhooks


def list_webhooks(session: Session, building_id: str) -> list[WebhookRow]:
    stmt = select(WebhookRow).where(WebhookRow.building_id == building_id).order_by(WebhookRow.id)
    return list(session.execute(stmt).scalars())


def get_webhook(session: Session, building_id: str, webhook_id: str) -> WebhookRow | None:
    return session.get(WebhookRow, (building_id, webhook_id))


def save_webhook(session: Session, row: dict[str, Any]) -> None:
    """Insert or replace a webhook; a suspended one takes events again."""
    values = {**row, "suspended_at": None, "updated_at": datetime.now(UTC)}
    upsert(session, WebhookRow, [values], ["building_id", "id"])


def delete_webhook(session: Session, building_id: str, webhook_id: str) -> bool:
    """Delete a webhook and its delivery log; whether it existed."""
    session.execute(
        delete(WebhookDeliveryRow).where(
            WebhookDeliveryRow.building_id == building_id, WebhookDeliveryRow.webhook_id == webhook_id
        )
    )
    result = session.execute(
        delete(WebhookRow).where(WebhookRow.building_id == building_id, WebhookRow.id == webhook_id)
    )
    return bool(cast(CursorResult[Any], result).rowcount)


_ACTIVE_HOOKS = select(WebhookRow.id, WebhookRow.events).where(
    WebhookRow.building_id == bindparam("b"), WebhookRow.suspended_at.is_(None)
)
_DELIVERY = insert(WebhookDeliveryRow)


def active_webhooks(session: Session, building_id: str) -> list[tuple[str, str]]:
    """The building's webhooks that take events: (id, events taken, comma-separated)."""
    return [(str(i), str(e)) for i, e in session.connection().execute(_ACTIVE_HOOKS, {"b": building_id})]


def enqueue_deliveries(
    session: Session,
    building_id: str,
    hooks: Sequence[tuple[str, str]],
    events: Sequence[tuple[str, str]],
    now_ms: int,
) -> int:
    """In the transaction of the change that caused them: each event ``(name, body)`` queued for every one
    of ``hooks`` (``active_webhooks``) that takes it; how many deliveries were queued."""
    rows = [
        {
            "building_id": building_id,
            "webhook_id": hook_id,
            "event": name,
            "body": body,
            "created_ms": now_ms,
            "attempts": 0,
            "status": "pending",
            "next_attempt_ms": now_ms,
        }
        for name, body in events
        for hook_id, takes in hooks
        if name in takes.split(",")
    ]
    execute_many(session, _DELIVERY, rows)
    return len(rows)


def webhook_deliveries(
    session: Session, building_id: str, webhook_id: str, limit: int
) -> list[WebhookDeliveryRow]:
    """The webhook's latest deliveries, newest first."""
    stmt = (
        select(WebhookDeliveryRow)
        .where(WebhookDeliveryRow.building_id == building_id, WebhookDeliveryRow.webhook_id == webhook_id)
        .order_by(WebhookDeliveryRow.id.desc())
        .limit(limit)
    )
    return list(session.execute(stmt).scalars())


def claim_due_deliveries(session: Session, now_ms: int, hold_ms: int, limit: int) -> list[WebhookDeliveryRow]:
    """Claim, for up to ``limit`` webhooks, the oldest pending delivery when it is due and nobody holds it:
    a webhook's deliveries go one at a time, in order. Each claim is a conditional update, so of several
    dispatchers (a cluster's fronts) one takes it."""
    heads = (
        select(func.min(WebhookDeliveryRow.id))
        .where(WebhookDeliveryRow.status == "pending")
        .group_by(WebhookDeliveryRow.building_id, WebhookDeliveryRow.webhook_id)
    )
    rows = session.execute(
        select(WebhookDeliveryRow)
        .where(
            WebhookDeliveryRow.id.in_(heads),
            WebhookDeliveryRow.next_attempt_ms <= now_ms,
            WebhookDeliveryRow.claimed_until_ms.is_(None) | (WebhookDeliveryRow.claimed_until_ms < now_ms),
        )
        .order_by(WebhookDeliveryRow.id)
        .limit(limit)
    ).scalars()
    claimed = []
    for row in list(rows):
        result = session.execute(
            update(WebhookDeliveryRow)
            .where(
                WebhookDeliveryRow.id == row.id,
                WebhookDeliveryRow.status == "pending",
                WebhookDeliveryRow.claimed_until_ms.is_(None)
                | (WebhookDeliveryRow.claimed_until_ms < now_ms),
            )
            .values(claimed_until_ms=now_ms + hold_ms)
        )
        if cast(CursorResult[Any], result).rowcount:
            claimed.append(row)
    return claimed


def finish_attempt(session: Session, delivery_id: int, **values: Any) -> None:
    """Record a try of a delivery (its status, answer, error, next try) and release it."""
    session.execute(
        update(WebhookDeliveryRow)
        .where(WebhookDeliveryRow.id == delivery_id)
        .values(**values, claimed_until_ms=None, attempts=WebhookDeliveryRow.attempts + 1)
    )


def suspend_webhook(session: Session, building_id: str, webhook_id: str, reason: str) -> None:
    """A delivery gave up: the webhook takes no new events, and its pending ones are given up."""
    session.execute(
        update(WebhookRow)
        .where(WebhookRow.building_id == building_id, WebhookRow.id == webhook_id)
        .values(suspended_at=datetime.now(UTC))
    )
    session.execute(
        update(WebhookDeliveryRow)
        .where(
            WebhookDeliveryRow.building_id == building_id,
            WebhookDeliveryRow.webhook_id == webhook_id,
            WebhookDeliveryRow.status == "pending",
        )
        .values(status="gave_up", error=reason, next_attempt_ms=None, claimed_until_ms=None)
    )


def prune_deliveries(session: Session, before_ms: int, limit: int) -> int:
    """Delete at most ``limit`` finished deliveries created before ``before_ms``."""
    doomed = (
        select(WebhookDeliveryRow.id)
        .where(WebhookDeliveryRow.created_ms < before_ms, WebhookDeliveryRow.status != "pending")
        .limit(limit)
        .scalar_subquery()
    )
    result = session.execute(delete(WebhookDeliveryRow).where(WebhookDeliveryRow.id.in_(doomed)))
    return int(cast(CursorResult[Any], result).rowcount or 0)


# ----------------------------------------------------------------------------- keys


def hash_key(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def insert_key(
    session: Session, prefix: str, secret: str, scope: str, building_id: str | None, device_id: str | None
) -> ApiKeyRow:
    row = ApiKeyRow(
        prefix=prefix, key_hash=hash_key(secret), scope=scope, building_id=building_id, device_id=device_id
    )
    session.add(row)
    session.flush()
    return row


def find_key(session: Session, secret: str) -> ApiKeyRow | None:
    stmt = select(ApiKeyRow).where(ApiKeyRow.key_hash == hash_key(secret), ApiKeyRow.revoked_at.is_(None))
    return session.execute(stmt).scalar_one_or_none()


def valid_key_ids(session: Session, key_ids: Collection[int], chunk: int = 500) -> set[int]:
    """Those of these keys that exist and are not revoked."""
    ids = sorted(key_ids)
    valid: set[int] = set()
    for start in range(0, len(ids), chunk):
        stmt = select(ApiKeyRow.id).where(
            ApiKeyRow.id.in_(ids[start : start + chunk]), ApiKeyRow.revoked_at.is_(None)
        )
        valid.update(int(i) for i in session.execute(stmt).scalars())
    return valid


def _of_building(building_id: str | None) -> ColumnElement[bool]:
    """Keys of this building, or (``None``) the site-wide ones."""
    if building_id is None:
        return ApiKeyRow.building_id.is_(None)
    return ApiKeyRow.building_id == building_id


def list_keys(session: Session, building_id: str | None) -> list[ApiKeyRow]:
    """A building's keys (``None``: the site-wide ones), oldest first, revoked ones included."""
    stmt = select(ApiKeyRow).where(_of_building(building_id)).order_by(ApiKeyRow.id)
    return list(session.execute(stmt).scalars())


def revoke_keys(session: Session, building_id: str | None, prefix: str) -> list[int]:
    """Revoke the live keys of a building (``None``: site-wide) with this prefix; returns their ids."""
    stmt = (
        update(ApiKeyRow)
        .where(_of_building(building_id), ApiKeyRow.prefix == prefix, ApiKeyRow.revoked_at.is_(None))
        .values(revoked_at=func.now())
        .returning(ApiKeyRow.id)
    )
    return [int(i) for i in session.execute(stmt).scalars()]


def touch_keys(session: Session, last_used: Mapping[int, datetime]) -> None:
    """Record when keys were last used: one statement per distinct time (the cache keeps minutes, so a
    round of thousands of keys is a statement or two)."""
    by_time: dict[datetime, list[int]] = {}
    for key_id, used in last_used.items():
        by_time.setdefault(used, []).append(key_id)
    for used, ids in by_time.items():
        session.execute(update(ApiKeyRow).where(ApiKeyRow.id.in_(ids)).values(last_used_at=used))


# ----------------------------------------------------------------------------- devices


def devices(session: Session, building_id: str) -> dict[str, tuple[str, str | None, int | None, int | None]]:
    """The building's devices: id -> (user id, Bluetooth advertised id, last applied sequence number, the
    install it counts in)."""
    stmt = select(
        DeviceRow.id, DeviceRow.user_id, DeviceRow.ble_advertised_id, DeviceRow.last_seq, DeviceRow.install_ms
    ).where(DeviceRow.building_id == building_id)
    return {
        device: (user, ble, None if seq is None else int(seq), None if install is None else int(install))
        for device, user, ble, seq, install in session.execute(stmt)
    }


def upsert_devices(session: Session, rows: Sequence[dict[str, object]]) -> None:
    """Create or update many devices in one statement. Each row gives building_id, id, user_id,
    ble_advertised_id, last_seq and install_ms; the caller passes only sequence numbers that advance (or
    start again in a later install)."""
    upsert(session, DeviceRow, list(rows), ["building_id", "id"], keep_when_null=("ble_advertised_id",))


# ----------------------------------------------------------------------------- anchors


def list_anchors(session: Session, building_id: str) -> list[AnchorRow]:
    stmt = select(AnchorRow).where(AnchorRow.building_id == building_id).order_by(AnchorRow.id)
    return list(session.execute(stmt).scalars())


def get_anchor(session: Session, building_id: str, public_id: str) -> AnchorRow | None:
    stmt = select(AnchorRow).where(AnchorRow.building_id == building_id, AnchorRow.public_id == public_id)
    return session.execute(stmt).scalar_one_or_none()


def save_anchor(session: Session, row: AnchorRow) -> None:
    """Insert or update by (building, public id)."""
    existing = get_anchor(session, row.building_id, row.public_id)
    if existing is None:
        session.add(row)
        return
    for name in (
        "floor",
        "type",
        "x_m",
        "y_m",
        "cov_xx",
        "cov_xy",
        "cov_yy",
        "observation_count",
        "known",
        "label",
        "last_seen_ms",
        "signature",
    ):
        setattr(existing, name, getattr(row, name))


def delete_anchor(session: Session, building_id: str, public_id: str) -> bool:
    result = session.execute(
        delete(AnchorRow).where(AnchorRow.building_id == building_id, AnchorRow.public_id == public_id)
    )
    return bool(getattr(result, "rowcount", 0))


# ----------------------------------------------------------------------------- positions


# executed on the driver (``execute_many``): the ORM's bulk path, and Core's per-row parameters, cost more
# than the rows; inline: nothing is fetched back (PostgreSQL would otherwise return each row's id)
_POSITIONS_INSERT = insert(PositionSnapshotRow).inline()


def add_positions(
    session: Session, rows: Sequence[dict[str, object]], history: Sequence[bool] | None = None
) -> None:
    """Each user's latest position kept apart (rows in time order per user; ``stored_at_ms`` left out), and
    the rows ``history`` marks (all when None) added to the position history, in one executemany (column
    name -> value per row)."""
    if not rows:
        return
    kept = rows if history is None else [r for r, keep in zip(rows, history, strict=True) if keep]
    execute_many(session, _POSITIONS_INSERT, kept)
    latest = {str(r["user_id"]): {k: v for k, v in r.items() if k != "stored_at_ms"} for r in rows}
    upsert(session, LatestPositionRow, list(latest.values()), ["building_id", "user_id"])


def delete_user_positions(session: Session, building_id: str, user_id: str) -> int:
    """Delete a user's latest position and its whole history; the number of rows deleted."""
    deleted = 0
    for table in (LatestPositionRow, PositionSnapshotRow):
        result = session.execute(
            delete(table).where(table.building_id == building_id, table.user_id == user_id)
        )
        deleted += cast(CursorResult[Any], result).rowcount
    return deleted


def latest_positions(session: Session, building_id: str) -> list[LatestPositionRow]:
    """Every user's latest snapshot in the building."""
    stmt = (
        select(LatestPositionRow)
        .where(LatestPositionRow.building_id == building_id)
        .order_by(LatestPositionRow.user_id)
    )
    return list(session.execute(stmt).scalars())


def latest_positions_of(
    session: Session, building_id: str, users: Collection[str]
) -> list[LatestPositionRow]:
    """The latest snapshots of these users (those that have one)."""
    stmt = select(LatestPositionRow).where(
        LatestPositionRow.building_id == building_id, LatestPositionRow.user_id.in_(list(users))
    )
    return list(session.execute(stmt).scalars())


def device_user(session: Session, building_id: str, device_id: str) -> str | None:
    """The user a device posts as (its own id unless assigned); None for a device that has posted nothing."""
    stmt = select(DeviceRow.user_id).where(DeviceRow.building_id == building_id, DeviceRow.id == device_id)
    return session.execute(stmt).scalar_one_or_none()


def prune_history(
    session: Session,
    building_id: str,
    positions_before_ms: int | None,
    batches_before: datetime | None,
    limit: int,
) -> tuple[int, int]:
    """Delete at most ``limit`` position snapshots stored before ``positions_before_ms`` and at most
    ``limit`` batch ids received before ``batches_before`` whose body is no longer logged (the log a
    restart replays is never pruned); None keeps that history. Returns how many of each went."""
    positions = batches = 0
    if positions_before_ms is not None:
        positions = _delete_some(
            session,
            PositionSnapshotRow,
            building_id,
            PositionSnapshotRow.stored_at_ms < positions_before_ms,
            limit,
        )
    if batches_before is not None:
        batches = _delete_some(
            session,
            BatchRow,
            building_id,
            (BatchRow.received_at < batches_before)
            & ~exists().where(BatchLogRow.batch_row_id == BatchRow.id),
            limit,
        )
    return positions, batches


def prune_visits(session: Session, building_id: str, before_ms: int, limit: int) -> int:
    """Delete at most ``limit`` closed zone visits entered (stored) before ``before_ms``: they go with the
    position history they came from. Open ones stay, however old."""
    old = (ZoneVisitRow.stored_at_ms < before_ms) & ZoneVisitRow.left_ms.is_not(None)
    return _delete_some(session, ZoneVisitRow, building_id, old, limit)


def _delete_some(
    session: Session,
    table: type[PositionSnapshotRow] | type[BatchRow] | type[ZoneVisitRow],
    building_id: str,
    old: ColumnElement[bool],
    limit: int,
) -> int:
    doomed = select(table.id).where(table.building_id == building_id, old).limit(limit).scalar_subquery()
    return int(session.connection().execute(delete(table).where(table.id.in_(doomed))).rowcount or 0)


def position_history(
    session: Session, building_id: str, user_id: str, since_ms: int, until_ms: int, limit: int
) -> list[PositionSnapshotRow]:
    stmt = (
        select(PositionSnapshotRow)
        .where(
            PositionSnapshotRow.building_id == building_id,
            PositionSnapshotRow.user_id == user_id,
            PositionSnapshotRow.t_ms >= since_ms,
            PositionSnapshotRow.t_ms <= until_ms,
        )
        .order_by(PositionSnapshotRow.t_ms, PositionSnapshotRow.id)
        .limit(limit)
    )
    return list(session.execute(stmt).scalars())


def positions_at(session: Session, building_id: str, at_ms: int, window_ms: int) -> list[PositionSnapshotRow]:
    """Each user's latest snapshot in ``[at_ms - window_ms, at_ms]``: the building as it was at ``at_ms``."""
    in_window = (
        PositionSnapshotRow.building_id == building_id,
        PositionSnapshotRow.t_ms >= at_ms - window_ms,
        PositionSnapshotRow.t_ms <= at_ms,
    )
    newest = (
        select(PositionSnapshotRow.user_id, func.max(PositionSnapshotRow.id).label("id"))
        .where(*in_window)
        .group_by(PositionSnapshotRow.user_id)
        .subquery()
    )
    stmt = (
        select(PositionSnapshotRow)
        .join(newest, PositionSnapshotRow.id == newest.c.id)
        .order_by(PositionSnapshotRow.user_id)
    )
    return list(session.execute(stmt).scalars())


def recent_tracks(session: Session, building_id: str, since_ms: int, limit: int) -> list[PositionSnapshotRow]:
    stmt = (
        select(PositionSnapshotRow)
        .where(PositionSnapshotRow.building_id == building_id, PositionSnapshotRow.t_ms >= since_ms)
        .order_by(PositionSnapshotRow.user_id, PositionSnapshotRow.t_ms)
        .limit(limit)
    )
    return list(session.execute(stmt).scalars())


# ----------------------------------------------------------------------------- tracker snapshots


def load_tracker_snapshot(session: Session, building_id: str) -> TrackerSnapshotRow | None:
    return session.get(TrackerSnapshotRow, building_id)


def save_tracker_snapshot(
    session: Session, building_id: str, format_version: int, tracker_call: int, state: bytes
) -> None:
    """Replace the building's snapshot (one row per building)."""
    row = session.get(TrackerSnapshotRow, building_id)
    if row is None:
        session.add(
            TrackerSnapshotRow(
                building_id=building_id,
                format_version=format_version,
                tracker_call=tracker_call,
                state=state,
            )
        )
        return
    row.format_version = format_version
    row.tracker_call = tracker_call
    row.state = state
    row.taken_at = datetime.now(UTC)
