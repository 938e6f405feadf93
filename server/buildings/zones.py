"""A building's zones as its operators draw them, and the visits its users' entries, exits and dwells make.

A zone is written with a snapshot in one transaction (like a floor plan), so a restart replays the batches
after it with the zone and none before it. The tracker's zone stage (``slam_core.tracking.zone_stage``)
decides the events from each user's particles; each event is stored in the transaction of the batch that
caused it (``record``), as the visit it opens, closes or marks, so visits survive a restart and a crash: a
replayed batch's events are in SQL already and are not stored again."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from sqlalchemy.orm import Session

from schemas.live import LiveMessage
from schemas.zones import MAX_ZONES, Zone, ZoneIn
from server.buildings.building import Building, SaveSnapshot, commit_with_snapshot
from server.errors import InvalidInputError, NotFoundError
from server.ingestion.zones import set_tracker_zones, stored_ring, webhook_events, wire_zone, zone_messages
from server.store import repositories as repo
from server.store.models import ZoneRow
from slam_core.tracking.batches import ZoneEvent

RESERVED_IDS = frozenset({"occupancy"})
"""Paths under ``/zones/`` that are not zones."""


class Zones:
    def __init__(self, building: Building, save_snapshot: SaveSnapshot, reload: Callable[[], None]) -> None:
        self.building = building
        self._save_snapshot = save_snapshot
        self._reload = reload

    def put(self, zone_id: str, body: ZoneIn) -> Zone:
        """Create or replace zone ``zone_id``: on one of the building's floors, a simple outline within its
        floor. Users inside a replaced zone stay inside until the next estimate decides (with events); the
        same zone again (a retry) changes nothing. Answers the zone as stored, with its occupancy."""
        b = self.building
        if zone_id in RESERVED_IDS:
            raise InvalidInputError(
                f"a zone may not be named {zone_id!r}: /zones/{zone_id} is another resource"
            )
        levels = [int(v) for v in b.tracker.levels]
        if body.floor not in levels:
            floors = ", ".join(map(str, levels))
            raise NotFoundError(f"building {b.building_id!r} has no floor {body.floor}; its floors: {floors}")
        with b.sessions() as session:
            size = {f.level: (f.width_m, f.height_m) for f in repo.list_floors(session, b.building_id)}
            rows = repo.list_zones(session, b.building_id)
            occupancy = repo.zone_occupancy(session, b.building_id).get(zone_id, 0)
        try:
            ring = stored_ring(zone_id, body, size.get(body.floor, (None, None)))
        except ValueError as exc:
            raise InvalidInputError(str(exc)) from None
        row = {
            "building_id": b.building_id,
            "id": zone_id,
            "floor": body.floor,
            "name": body.name,
            "ring": ring,
            "dwell_s": body.dwell_s,
        }
        others = [r for r in rows if r.id != zone_id]
        same = [r for r in rows if r.id == zone_id]
        if same and all(getattr(same[0], k) == v for k, v in row.items()):
            return wire_zone(same[0], occupancy)
        if len(others) >= MAX_ZONES:
            raise InvalidInputError(f"building {b.building_id!r} has {MAX_ZONES} zones, the most it may hold")
        new = ZoneRow(**row)
        set_tracker_zones(b.tracker, [*others, new])
        commit_with_snapshot(b, self._save_snapshot, self._reload, lambda s: repo.save_zone(s, row))
        return wire_zone(new, occupancy)

    def delete(self, zone_id: str) -> None:
        """Delete a zone and its visits; users inside it are inside nothing, without events."""
        b = self.building
        with b.sessions() as session:
            rows = repo.list_zones(session, b.building_id)
        if zone_id not in {r.id for r in rows}:
            raise NotFoundError(f"no zone {zone_id!r} in building {b.building_id!r}")
        set_tracker_zones(b.tracker, [r for r in rows if r.id != zone_id])
        commit_with_snapshot(
            b, self._save_snapshot, self._reload, lambda s: repo.delete_zone(s, b.building_id, zone_id)
        )

    def record(self, session: Session, events: Sequence[ZoneEvent]) -> list[LiveMessage]:
        """In a group's transaction: the events of a tracker call stored as visits; their live messages."""
        if not events:
            return []
        b, now_ms = self.building, int(time.time() * 1000)
        repo.record_zone_events(
            session,
            b.building_id,
            [(e.user, e.zone_id, e.kind, e.t_ms, e.probability) for e in events],
            now_ms,
        )
        self._enqueue(session, events, now_ms)
        self.building.counters.zone_events += len(events)
        return zone_messages(events)

    def _enqueue(self, session: Session, events: Sequence[ZoneEvent], now_ms: int) -> None:
        """The events queued for the building's webhooks (an outbox: sent after the transaction commits, by
        ``server.webhooks.dispatcher``); nothing to build when it has none."""
        b = self.building
        hooks = repo.active_webhooks(session, b.building_id)
        if hooks:
            b.counters.webhook_deliveries += repo.enqueue_deliveries(
                session, b.building_id, hooks, webhook_events(b.building_id, events), now_ms
            )

    def close_lost(self, session: Session, users: Sequence[str]) -> list[LiveMessage]:
        """In a transaction that forgets idle ``users``: their open visits closed at their latest estimate's
        time (probability 0: the server no longer places them inside), and the exits told."""
        b = self.building
        if not users:
            return []
        closed = repo.close_lost_visits(session, b.building_id, users)
        events = [ZoneEvent(user, zone, "exit", left_ms, 0.0) for user, zone, left_ms in closed]
        b.counters.zone_events += len(events)
        self._enqueue(session, events, int(time.time() * 1000))
        return zone_messages(events)
