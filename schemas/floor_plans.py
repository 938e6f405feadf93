"""A floor's plan as GeoJSON (RFC 7946): the walkable area, obstacles and walls, in the building's local
frame or in WGS-84 through its geo-reference."""

from __future__ import annotations

import math
from enum import StrEnum
from typing import Annotated, Any, Literal, Self

from pydantic import Field, model_validator

from schemas.common import MAX_COORDINATE_M, WireModel, wire_config

MAX_PLAN_VERTICES = 200_000
"""Vertices a plan may hold in all: a mall floor's plan has a few thousand."""

Point = Annotated[
    tuple[float, float],
    Field(description="[x, y] in metres in the local frame, or [longitude, latitude] in degrees in WGS-84."),
]


class PlanKind(StrEnum):
    WALKABLE = "walkable"
    """Polygons: where people may be (the floor's outline, holes for courtyards and voids)."""
    OBSTACLE = "obstacle"
    """Polygons whose outlines are walls with unknown doors (shops, rooms)."""
    WALL = "wall"
    """Lines (or polygon outlines) that people cross only through doors the plan does not show."""


Ring = Annotated[
    list[Point],
    Field(min_length=4, description="A closed ring: at least four positions, the first repeated last."),
]


def _ring(ring: list[Point], where: str) -> None:
    if ring[0] != ring[-1]:
        raise ValueError(f"{where}: a ring must end at its first position")


class PolygonGeometry(WireModel):
    type: Literal["Polygon"]
    coordinates: list[Ring] = Field(min_length=1)

    @model_validator(mode="after")
    def _closed(self) -> Self:
        for i, ring in enumerate(self.coordinates):
            _ring(ring, f"ring {i}")
        return self


class MultiPolygonGeometry(WireModel):
    type: Literal["MultiPolygon"]
    coordinates: list[list[Ring]] = Field(min_length=1)

    @model_validator(mode="after")
    def _closed(self) -> Self:
        for p, polygon in enumerate(self.coordinates):
            if not polygon:
                raise ValueError(f"polygon {p} has no ring")
            for i, ring in enumerate(polygon):
                _ring(ring, f"polygon {p}, ring {i}")
        return self


class LineStringGeometry(WireModel):
    type: Literal["LineString"]
    coordinates: list[Point] = Field(min_length=2)


class MultiLineStringGeometry(WireModel):
    type: Literal["MultiLineString"]
    coordinates: list[Annotated[list[Point], Field(min_length=2)]] = Field(min_length=1)


Geometry = Annotated[
    PolygonGeometry | MultiPolygonGeometry | LineStringGeometry | MultiLineStringGeometry,
    Field(discriminator="type"),
]


class PlanProperties(WireModel):
    kind: PlanKind
    name: str | None = Field(default=None, max_length=128)


class PlanFeature(WireModel):
    type: Literal["Feature"]
    geometry: Geometry
    properties: PlanProperties
    id: str | int | None = None

    @model_validator(mode="after")
    def _kind_fits_geometry(self) -> Self:
        lines = isinstance(self.geometry, LineStringGeometry | MultiLineStringGeometry)
        if lines and self.properties.kind != PlanKind.WALL:
            raise ValueError(f"a {self.properties.kind} feature must be a Polygon or MultiPolygon")
        return self

    def rings(self) -> list[list[Point]]:
        """Polygon rings (outlines and holes), or none for lines."""
        g = self.geometry
        if isinstance(g, PolygonGeometry):
            return list(g.coordinates)
        if isinstance(g, MultiPolygonGeometry):
            return [ring for polygon in g.coordinates for ring in polygon]
        return []

    def lines(self) -> list[list[Point]]:
        """Polylines of a line feature, or none for polygons."""
        g = self.geometry
        if isinstance(g, LineStringGeometry):
            return [list(g.coordinates)]
        if isinstance(g, MultiLineStringGeometry):
            return [list(line) for line in g.coordinates]
        return []


FLOOR_PLAN_EXAMPLE: dict[str, Any] = {
    "type": "FeatureCollection",
    "frame": "local",
    "features": [
        {
            "type": "Feature",
            "properties": {"kind": "walkable", "name": "Ground floor"},
            "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [60, 0], [60, 50], [0, 50], [0, 0]]]},
        },
        {
            "type": "Feature",
            "properties": {"kind": "obstacle", "name": "Cafe"},
            "geometry": {
                "type": "Polygon",
                "coordinates": [[[10, 10], [20, 10], [20, 18], [10, 18], [10, 10]]],
            },
        },
        {
            "type": "Feature",
            "properties": {"kind": "wall"},
            "geometry": {"type": "LineString", "coordinates": [[30, 0], [30, 35]]},
        },
    ],
}


class FloorPlan(WireModel):
    """A floor's plan (``PUT /v1/buildings/{id}/floors/{level}/plan``). ``frame`` says how positions read:
    ``local`` (metres, x east and y north of the building's origin) or ``wgs84`` ([longitude, latitude],
    placed through the building's geo-reference). The server keeps and returns it in the local frame."""

    model_config = wire_config(FLOOR_PLAN_EXAMPLE)

    type: Literal["FeatureCollection"]
    frame: Literal["local", "wgs84"] = "local"
    features: list[PlanFeature] = Field(min_length=1, max_length=20_000)

    @model_validator(mode="after")
    def _bounded(self) -> Self:
        vertices = sum(len(r) for f in self.features for r in (*f.rings(), *f.lines()))
        if vertices > MAX_PLAN_VERTICES:
            raise ValueError(f"the plan has {vertices} vertices; at most {MAX_PLAN_VERTICES} are accepted")
        points = (p for f in self.features for r in (*f.rings(), *f.lines()) for p in r)
        if self.frame == "local":
            for x, y in points:
                if not (math.isfinite(x) and math.isfinite(y)) or max(abs(x), abs(y)) > MAX_COORDINATE_M:
                    raise ValueError(
                        f"position [{x}, {y}] is farther than {MAX_COORDINATE_M:g} m from the origin"
                    )
        else:
            for lon, lat in points:
                if not (-180.0 <= lon <= 180.0 and -90.0 <= lat <= 90.0):
                    raise ValueError(f"position [{lon}, {lat}] is not a WGS-84 [longitude, latitude]")
        return self
