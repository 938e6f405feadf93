"""crowdslam wire contract, version 1: pydantic models shared by REST, WebSocket and MCAP channels."""

from schemas.anchors import AnchorMergeIn, AnchorType, BuildingAnchor, KnownAnchorIn
from schemas.buildings import Building, Floor, GeoReference
from schemas.common import Position
from schemas.errors import FieldProblem, Problem
from schemas.estimates import EncounterEvent, EncounterModelName, Estimate, EstimateSource
from schemas.live import AnchorMessage, EncounterMessage, HeartbeatMessage, LiveMessage, PositionMessage
from schemas.sensors import SensorBatch

SCHEMA_VERSION = "1"

__all__ = [
    "SCHEMA_VERSION",
    "AnchorMergeIn",
    "AnchorMessage",
    "AnchorType",
    "Building",
    "BuildingAnchor",
    "EncounterEvent",
    "EncounterMessage",
    "EncounterModelName",
    "Estimate",
    "EstimateSource",
    "FieldProblem",
    "Floor",
    "GeoReference",
    "HeartbeatMessage",
    "KnownAnchorIn",
    "LiveMessage",
    "Position",
    "PositionMessage",
    "Problem",
    "SensorBatch",
]
