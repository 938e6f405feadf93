"""Floor plans from the wire (GeoJSON, local or WGS-84) to the local frame and to the engine's index."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from schemas.floor_plans import FloorPlan, PlanKind, Point
from server.ingestion.extent import Extent
from slam_core.filter.floor_plan import PlanIndex
from slam_core.geo import GeoFrame


def to_local(plan: FloorPlan, geo: GeoFrame | None, extent: Extent | None) -> FloorPlan:
    """The plan in the building's local frame, every position within its extent; ``ValueError`` saying why
    not (a WGS-84 plan of a building without a geo-reference, a position outside the building)."""
    if plan.frame == "wgs84":
        if geo is None:
            raise ValueError("the plan is in WGS-84 but the building has no geo-reference to place it")
        frame = geo

        def place(p: Point) -> list[float]:
            x, y = frame.to_local(p[1], p[0])
            return [round(x, 3), round(y, 3)]

        raw = plan.model_dump(mode="json")
        for feature in raw["features"]:
            feature["geometry"]["coordinates"] = map_positions(feature["geometry"]["coordinates"], place)
        raw["frame"] = "local"
        plan = FloorPlan.model_validate(raw)
    if extent is not None:
        for f, feature in enumerate(plan.features):
            for part in (*feature.rings(), *feature.lines()):
                for x, y in part:
                    refusal = extent.refusal(f"features.{f}: the position", x, y)
                    if refusal is not None:
                        raise ValueError(refusal)
    return plan


def map_positions(coordinates: Any, place: Callable[[Any], list[float]]) -> Any:
    """``coordinates`` of any GeoJSON geometry with each position replaced by ``place``'s."""
    if coordinates and isinstance(coordinates[0], int | float):
        return place(coordinates)
    return [map_positions(c, place) for c in coordinates]


def engine_plan(plan: FloorPlan) -> PlanIndex:
    """The engine's index of a local-frame plan: walls from wall features and obstacles' outlines, the
    walkable area from walkable polygons (their outlines are not walls: a particle outside may come back)."""
    if plan.frame != "local":
        raise ValueError("the engine takes plans in the local frame (to_local)")
    segments: list[np.ndarray] = []
    rings: list[np.ndarray] = []
    for feature in plan.features:
        kind = feature.properties.kind
        for ring in feature.rings():
            points = np.asarray(ring, dtype=np.float64)
            if kind == PlanKind.WALKABLE:
                rings.append(points[:-1])
            else:
                segments.append(np.hstack([points[:-1], points[1:]]))
        for line in feature.lines():
            points = np.asarray(line, dtype=np.float64)
            segments.append(np.hstack([points[:-1], points[1:]]))
    walls = np.concatenate(segments) if segments else np.zeros((0, 4))
    return PlanIndex.build(walls, rings)
