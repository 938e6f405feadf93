"""Zones between the wire, the store and the engine: an operator's polygon checked and kept as its ring, a
stored zone as the tracker's zone stage and the API read it, and the stage's events as live messages."""

from __future__ import annotations

import json
import uuid
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from schemas.live import LiveMessage, ZoneMessage
from schemas.zones import WebhookPayload, Zone, ZoneIn, ZonePolygon
from slam_core.tracking.batches import ZoneEvent
from slam_core.tracking.tracker import BuildingTracker
from slam_core.zones.geometry import ring_problem


class StoredZone(Protocol):
    """A zone as the store keeps it (``server.store.models.ZoneRow``): its outline as a JSON list of [x, y]
    in the local frame, the ring not closed."""

    id: str
    floor: int
    name: str
    ring: str
    dwell_s: float | None


ON_FLOOR_M = 1.0
"""How far a zone's corner may lie outside its floor's rectangle (a line drawn on the floor's edge)."""


def stored_ring(zone_id: str, body: ZoneIn, floor_size_m: tuple[float | None, float | None]) -> str:
    """The zone's outline as stored: a simple polygon on its floor (within ``0..width`` east and
    ``0..height`` north, where the floor's size is known: the margin a fix may take outside the door is no
    place for a zone); ``ValueError`` saying why not (naming the zone)."""
    ring = np.asarray(body.polygon.coordinates[0][:-1], dtype=np.float64)
    problem = ring_problem(ring)
    if problem is not None:
        raise ValueError(f"zone {zone_id!r}: {problem}")
    width, height = floor_size_m
    if width is not None and height is not None:
        for x, y in ring.tolist():
            if not (-ON_FLOOR_M <= x <= width + ON_FLOOR_M and -ON_FLOOR_M <= y <= height + ON_FLOOR_M):
                raise ValueError(
                    f"zone {zone_id!r}'s corner ({x:g}, {y:g}) m is outside the building's floor "
                    f"{body.floor}, which spans x 0..{width:g} m and y 0..{height:g} m"
                )
    return json.dumps(ring.tolist())


def ring_of(zone: StoredZone) -> np.ndarray:
    """A stored zone's outline (K, 2), the ring not closed."""
    return np.asarray(json.loads(zone.ring), dtype=np.float64).reshape(-1, 2)


def set_tracker_zones(tracker: BuildingTracker, zones: Sequence[StoredZone]) -> None:
    """The tracker's zones as stored (all of the building's)."""
    tracker.zones.set_zones(
        [z.id for z in zones],
        [ring_of(z) for z in zones],
        [z.floor for z in zones],
        [None if z.dwell_s is None else round(z.dwell_s * 1000) for z in zones],
    )


def wire_zone(zone: StoredZone, occupancy: int) -> Zone:
    ring = [(x, y) for x, y in ring_of(zone).tolist()]
    return Zone(
        id=zone.id,
        floor=zone.floor,
        name=zone.name,
        polygon=ZonePolygon(type="Polygon", coordinates=[[*ring, ring[0]]]),
        dwell_s=zone.dwell_s,
        occupancy=occupancy,
    )


def webhook_events(building_id: str, events: Sequence[ZoneEvent]) -> list[tuple[str, str]]:
    """Each event as a webhook delivers it: its name and its JSON body (``WebhookPayload``)."""
    out: list[tuple[str, str]] = []
    for e in events:
        payload = WebhookPayload.model_validate(
            {
                "id": uuid.uuid4().hex,
                "event": f"zone.{e.kind}",
                "building_id": building_id,
                "zone_id": e.zone_id,
                "user_id": e.user,
                "t_ms": e.t_ms,
                "probability": min(1.0, max(0.0, e.probability)),
            }
        )
        out.append((payload.event, payload.model_dump_json()))
    return out


def zone_messages(events: Sequence[ZoneEvent]) -> list[LiveMessage]:
    return [
        ZoneMessage.model_validate(
            {
                "zone_id": e.zone_id,
                "user_id": e.user,
                "kind": e.kind,
                "t_ms": e.t_ms,
                "probability": min(1.0, max(0.0, e.probability)),
            }
        )
        for e in events
    ]
