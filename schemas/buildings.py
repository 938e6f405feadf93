"""Buildings, their floors and the geo-reference between local metres and WGS-84."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from schemas.common import Identifier, WireModel, wire_config


class GeoReference(WireModel):
    """Local frame (x east, y north after rotation, metres) anchored at a WGS-84 origin. A local point
    (x, y) is rotated counter-clockwise by ``rotation_rad`` into east/north metres, then offset from the
    origin on a local tangent plane (accurate to centimetres over a building)."""

    origin_lat_deg: float = Field(ge=-90.0, le=90.0)
    origin_lon_deg: float = Field(ge=-180.0, le=180.0)
    rotation_rad: float = Field(default=0.0, ge=-7.0, le=7.0)


class Floor(WireModel):
    level: int = Field(ge=-20, le=200, description="0 is the ground floor, negative below ground.")
    name: str = Field(min_length=1, max_length=64)
    elevation_m: float | None = Field(default=None, ge=-200.0, le=1000.0)
    width_m: float | None = Field(default=None, gt=0.0, le=5000.0)
    height_m: float | None = Field(default=None, gt=0.0, le=5000.0)


BUILDING_EXAMPLE: dict[str, Any] = {
    "id": "hq",
    "name": "HQ",
    "geo_reference": {"origin_lat_deg": 40.684492, "origin_lon_deg": -74.401406, "rotation_rad": 0.0},
    "floors": [{"level": 0, "name": "Ground", "width_m": 60.0, "height_m": 50.0}],
}


class Building(WireModel):
    model_config = wire_config(BUILDING_EXAMPLE)

    id: Identifier
    name: str = Field(min_length=1, max_length=128)
    geo_reference: GeoReference | None = None
    floors: list[Floor] = Field(default_factory=list, max_length=250)


class DeviceAssignment(WireModel):
    """Which user a device's batches are for. A device posts as its own id, or as the user it first posted
    as; an operator assigns it another (``PUT /v1/buildings/{id}/devices/{device}``)."""

    device_id: Identifier
    user_id: Identifier


class DeviceAssignmentIn(WireModel):
    user_id: Identifier
