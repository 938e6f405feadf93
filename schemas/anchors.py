"""Building anchors: points with a recognisable sensor signature, learned by the crowd or pinned."""

from __future__ import annotations

from enum import StrEnum
from typing import Any, Literal, Self

from pydantic import Field, model_validator

from schemas.common import Covariance2, Identifier, Position, TimeMs, WireModel, wire_config


class AnchorType(StrEnum):
    """Anchor types. The first five are the paper testbed's; the rest come from the sensor front-end."""

    ELEVATOR = "elevator"
    STAIRS = "stairs"
    DOOR = "door"
    TURN = "turn"
    MAGNETIC = "magnetic"
    ESCALATOR = "escalator"
    BEACON = "beacon"
    WIFI = "wifi"
    ORGANIC = "organic"
    TAG = "tag"


ANCHOR_EXAMPLE: dict[str, Any] = {
    "id": "a-17",
    "building_id": "hq",
    "floor": 0,
    "type": "elevator",
    "position": {"x_m": 20.0, "y_m": 10.0},
    "covariance_m2": [[0.25, 0.0], [0.0, 0.25]],
    "observation_count": 41,
    "known": False,
    "label": None,
    "last_seen_ms": 1796559880500,
}


class BuildingAnchor(WireModel):
    """One anchor of a building's shared (crowd) map."""

    model_config = wire_config(ANCHOR_EXAMPLE)

    id: Identifier
    building_id: Identifier
    floor: int = Field(ge=-20, le=200)
    type: AnchorType
    position: Position
    covariance_m2: Covariance2
    observation_count: int = Field(ge=0)
    known: bool = Field(description="True when an operator entered its exact position.")
    label: str | None = Field(default=None, max_length=128)
    last_seen_ms: TimeMs | None = None
    signature: str | None = Field(
        default=None,
        max_length=128,
        description="The transmitter a radio-signature anchor stands for (`beacon:<mac>`, `wifi:<bssid>`); "
        "such anchors are matched by identity, not by position.",
        examples=["beacon:c4:4f:33:12:34:56"],
    )


class KnownAnchorIn(WireModel):
    """An operator pins an anchor at an exact position (DynamicSLAM Theorem 3 needs at least one)."""

    floor: int = Field(default=0, ge=-20, le=200)
    type: AnchorType
    position: Position
    label: str | None = Field(default=None, max_length=128)


class AnchorMergeIn(WireModel):
    """Merge anchors that the crowd learned twice into the first one."""

    anchor_ids: list[Identifier] = Field(
        min_length=2,
        max_length=50,
        json_schema_extra={"uniqueItems": True},
        description="Distinct anchor ids; the first one is kept.",
    )

    @model_validator(mode="after")
    def _distinct(self) -> Self:
        if len(set(self.anchor_ids)) != len(self.anchor_ids):
            raise ValueError("anchor_ids must be distinct")
        return self


class GeoJsonExport(WireModel):
    """``GET .../export.geojson``: the anchors as points (``properties.kind`` ``anchor``, with the anchor's
    fields) and recent tracks as lines (``kind`` ``track``, with ``user_id``), in WGS-84
    ([longitude, latitude], RFC 7946)."""

    type: Literal["FeatureCollection"] = "FeatureCollection"
    features: list[dict[str, Any]]
