"""A building's floor plans, as its operators upload them: stored in the local frame and weighing the steps of
the users on their floor from the next batch on. A plan is written with a snapshot in one transaction, so a
restart replays the batches after it with the plan and none before it."""

from __future__ import annotations

from collections.abc import Callable

from schemas.floor_plans import FloorPlan
from server.buildings.building import Building, SaveSnapshot, commit_with_snapshot
from server.errors import InvalidInputError, NotFoundError
from server.ingestion import floor_plans as plan_frames
from server.store import repositories as repo


class FloorPlans:
    def __init__(self, building: Building, save_snapshot: SaveSnapshot, reload: Callable[[], None]) -> None:
        self.building = building
        self._save_snapshot = save_snapshot
        self._reload = reload

    def put(self, level: int, body: FloorPlan) -> FloorPlan:
        """Store floor ``level``'s plan, in the local frame and within the building's extent; returns it as
        stored. The same plan again (a retry) changes nothing."""
        b = self.building
        with b.sessions() as session:
            levels = [f.level for f in repo.list_floors(session, b.building_id)]
        if level not in levels:
            raise NotFoundError(
                f"building {b.building_id!r} has no floor {level}; its floors: "
                f"{', '.join(map(str, levels)) or 'none (create the building with floors)'}"
            )
        try:
            local = plan_frames.to_local(body, b.geo, b.extent)
            index = plan_frames.engine_plan(local)
        except ValueError as exc:
            raise InvalidInputError(f"the floor plan cannot be used: {exc}") from None
        stored = local.model_dump_json()
        with b.sessions() as session:
            if repo.floor_plan(session, b.building_id, level) == stored:
                return local
        b.tracker.set_floor_plan(index, level)
        commit_with_snapshot(
            b,
            self._save_snapshot,
            self._reload,
            lambda s: repo.save_floor_plan(s, b.building_id, level, stored),
        )
        return local
