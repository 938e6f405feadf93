"""What the server estimates: user positions with their uncertainty, and encounters between users."""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from pydantic import Field

from schemas.common import Covariance2, Identifier, Position, TimeMs, WireModel, wire_config


class EstimateSource(StrEnum):
    """Which estimator produced a position."""

    PDR = "pdr"
    SEMANTICSLAM = "semanticslam"
    DYNAMICSLAM = "dynamicslam"
    FIX = "fix"
    FINGERPRINT = "fingerprint"


ESTIMATE_EXAMPLE: dict[str, Any] = {
    "building_id": "hq",
    "user_id": "alice",
    "device_id": "phone-1",
    "t_ms": 1796559880500,
    "position": {"x_m": 12.4, "y_m": 30.1},
    "covariance_m2": [[0.64, 0.05], [0.05, 0.81]],
    "best_particle": {"x_m": 12.6, "y_m": 29.9},
    "heading_rad": 1.52,
    "floor": 0,
    "floor_probability": 1.0,
    "source": "dynamicslam",
    "lat_deg": 40.6845,
    "lon_deg": -74.4013,
}


class Estimate(WireModel):
    """A user's position at one time: the filter's weighted mean and its 2x2 covariance, plus the
    paper's maximum-weight particle."""

    model_config = wire_config(ESTIMATE_EXAMPLE)

    building_id: Identifier
    user_id: Identifier
    device_id: Identifier
    t_ms: TimeMs
    position: Position
    covariance_m2: Covariance2
    best_particle: Position | None = Field(
        default=None, description="The maximum-weight particle's position."
    )
    heading_rad: float = Field(
        ge=-7.0, le=7.0, description="Direction of travel, counter-clockwise from east."
    )
    floor: int = Field(default=0, ge=-20, le=200, description="The floor the filter believes the user is on.")
    floor_probability: float = Field(
        default=1.0,
        ge=0.0,
        le=1.0,
        description="How sure the filter is of that floor: below ~0.9 it hesitates between floors.",
    )
    source: EstimateSource
    lat_deg: float | None = Field(default=None, ge=-90.0, le=90.0)
    lon_deg: float | None = Field(default=None, ge=-180.0, le=180.0)


class EncounterModelName(StrEnum):
    """How an encounter was detected (DynamicSLAM Section 4.1.2)."""

    WIFI_EQ3 = "wifi-eq3"
    WIFI_FINGERPRINT = "wifi-fingerprint"
    BLUETOOTH = "bluetooth"


class EncounterEvent(WireModel):
    """Two users found near each other; each refines the other's position (a human anchor)."""

    building_id: Identifier
    t_ms: TimeMs
    user_a: Identifier
    user_b: Identifier
    model: EncounterModelName
    distance_m: float = Field(ge=0.0, le=200.0, description="Relative distance from the encounter model.")
    distance_sigma_m: float = Field(
        gt=0.0, le=200.0, description="Standard deviation of that distance (sqrt R)."
    )
    applied: bool = Field(description="False when the Mahalanobis gate rejected it as an outlier.")
    floor: int = Field(default=0, ge=-20, le=200, description="The floor the two met on.")
    position_a: Position | None = Field(
        default=None,
        description="Where ``user_a`` was at ``t_ms``, as its filter believed before the encounter.",
    )
    position_b: Position | None = Field(default=None, description="Where ``user_b`` was at ``t_ms``.")
