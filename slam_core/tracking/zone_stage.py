"""The tracker's zone stage: the building's zones (``slam_core.zones``) and who is in which, updated for the
users a call estimates, by their particles; the entries, exits and dwells they cause.

Zones are the operator's, by id; the stage keeps them in one ``ZoneSet`` and the presence by filter slot
and zone index. A user being placed (not yet reported) is in no zone. Pure numerics."""

from __future__ import annotations

import numpy as np

from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.tracking.batches import ZoneEvent
from slam_core.zones.geometry import ZoneSet, inside_shares, zone_set
from slam_core.zones.presence import KINDS, ZoneParams, ZonePresence


class ZoneStage:
    def __init__(self, params: ZoneParams | None = None) -> None:
        self.ids: list[str] = []
        self.zones = ZoneSet.empty()
        self.dwell_ms = np.zeros(0, dtype=np.int64)
        self.presence = ZonePresence(params)

    def __len__(self) -> int:
        return len(self.ids)

    def set_zones(
        self, ids: list[str], rings: list[np.ndarray], levels: list[int], dwell_ms: list[int | None]
    ) -> None:
        """The building's zones now (all of them, by id). A zone kept by its id keeps who is inside it (its
        outline may have changed: the next update decides, with events); a zone gone ends its visits
        without events. ValueError (naming the zone) for an outline that is no zone's, nothing changed."""
        if not len(ids) == len(rings) == len(levels) == len(dwell_ms) or len(set(ids)) != len(ids):
            raise ValueError("one outline, floor and dwell time per zone, each zone id once")
        zones = zone_set(rings, levels, ids)
        old = {zone_id: k for k, zone_id in enumerate(self.ids)}
        self.presence.renumber_zones(np.array([old.get(z, -1) for z in ids], dtype=np.int64))
        self.ids = list(ids)
        self.zones = zones
        self.dwell_ms = np.array([-1 if d is None else int(d) for d in dwell_ms], dtype=np.int64)

    def inside(self, filters: DynamicSlam, slots: np.ndarray) -> np.ndarray:
        """(U, Z): each slot's probability inside each zone (0 for another floor's)."""
        s, z = filters.state, self.zones
        slots = np.ascontiguousarray(slots, dtype=np.int64)
        return inside_shares(
            s.x, s.y, s.logw, slots, filters.levels[slots], z.level, z.start, z.vx, z.vy, z.bbox
        )

    def update(
        self, filters: DynamicSlam, users: list[str], slots: np.ndarray, t_ms: np.ndarray
    ) -> list[ZoneEvent]:
        """The users (their filter slots, their estimates' times) after a call: the events they cause, in
        user order, then zone order."""
        if not self.ids or not users:
            return []
        events = self.presence.update(slots, t_ms, self.inside(filters, slots), self.dwell_ms)
        name = dict(zip(np.asarray(slots).tolist(), users, strict=True))
        return [
            ZoneEvent(name[r], self.ids[z], KINDS[k], t, p, told)
            for r, z, k, t, p, told in zip(
                events.row.tolist(),
                events.zone.tolist(),
                events.kind.tolist(),
                events.t_ms.tolist(),
                events.probability.tolist(),
                events.told_ms.tolist(),
                strict=True,
            )
        ]

    def release(self, slots: np.ndarray) -> None:
        """Slots whose users left: inside nothing (the server ends their visits)."""
        self.presence.clear_rows(np.asarray(slots, dtype=np.int64))
