"""The public models, their JSON Schemas and examples, for client developers and the MCAP channels."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, TypeAdapter

from schemas.anchors import ANCHOR_EXAMPLE, AnchorMergeIn, BuildingAnchor, KnownAnchorIn
from schemas.api import KEY_CREATE_ADAPTER, BatchReceipt, DevicePosition, KeyCreated
from schemas.buildings import BUILDING_EXAMPLE, Building
from schemas.errors import PROBLEM_EXAMPLE, Problem
from schemas.estimates import ESTIMATE_EXAMPLE, EncounterEvent, Estimate
from schemas.floor_plans import FLOOR_PLAN_EXAMPLE, FloorPlan
from schemas.live import LIVE_MESSAGE_ADAPTER, LiveBatch
from schemas.sensors import BATCH_EXAMPLE, SensorBatch
from schemas.signal_maps import SIGNAL_MAP_JOB_EXAMPLE, SignalMapJob
from schemas.zones import WEBHOOK_EXAMPLE, ZONE_EXAMPLE, WebhookIn, WebhookPayload, Zone, ZoneIn, ZoneVisit

PUBLIC_MODELS: dict[str, type[BaseModel] | TypeAdapter[Any]] = {
    "SensorBatch": SensorBatch,
    "Estimate": Estimate,
    "EncounterEvent": EncounterEvent,
    "BuildingAnchor": BuildingAnchor,
    "KnownAnchorIn": KnownAnchorIn,
    "AnchorMergeIn": AnchorMergeIn,
    "Building": Building,
    "LiveMessage": LIVE_MESSAGE_ADAPTER,
    "LiveBatch": LiveBatch,
    "Problem": Problem,
    "BatchReceipt": BatchReceipt,
    "DevicePosition": DevicePosition,
    "KeyCreateIn": KEY_CREATE_ADAPTER,
    "KeyCreated": KeyCreated,
    "SignalMapJob": SignalMapJob,
    "FloorPlan": FloorPlan,
    "ZoneIn": ZoneIn,
    "Zone": Zone,
    "ZoneVisit": ZoneVisit,
    "WebhookIn": WebhookIn,
    "WebhookPayload": WebhookPayload,
}

EXAMPLES: dict[str, dict[str, Any]] = {
    "batch": BATCH_EXAMPLE,
    "estimate": ESTIMATE_EXAMPLE,
    "anchor": ANCHOR_EXAMPLE,
    "building": BUILDING_EXAMPLE,
    "problem": PROBLEM_EXAMPLE,
    "signal-map-job": SIGNAL_MAP_JOB_EXAMPLE,
    "floor-plan": FLOOR_PLAN_EXAMPLE,
    "zone": ZONE_EXAMPLE,
    "webhook": WEBHOOK_EXAMPLE,
}
"""Named examples, each valid against its model (a test checks)."""

EXAMPLE_MODELS: dict[str, type[BaseModel]] = {
    "batch": SensorBatch,
    "estimate": Estimate,
    "anchor": BuildingAnchor,
    "building": Building,
    "problem": Problem,
    "signal-map-job": SignalMapJob,
    "floor-plan": FloorPlan,
    "zone": ZoneIn,
    "webhook": WebhookIn,
}


def json_schemas() -> dict[str, dict[str, Any]]:
    """JSON Schema (draft 2020-12, validation mode) of every public model, keyed by file stem."""
    out: dict[str, dict[str, Any]] = {}
    for name, model in PUBLIC_MODELS.items():
        schema = model.json_schema() if isinstance(model, TypeAdapter) else model.model_json_schema()
        schema.setdefault("title", name)
        schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        schema["$id"] = f"https://crowdslam.dev/schemas/v1/{name}.json"
        out[name] = schema
    return out
