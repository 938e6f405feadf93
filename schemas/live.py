"""The live WebSocket envelope: one message per event, a discriminated union on ``type``; optionally many
per frame (``LiveBatch``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, TypeAdapter

from schemas.anchors import BuildingAnchor
from schemas.common import Identifier, TimeMs, WireModel
from schemas.estimates import EncounterEvent, Estimate
from schemas.zones import ZoneKind


class PositionMessage(WireModel):
    type: Literal["position"] = "position"
    estimate: Estimate


class EncounterMessage(WireModel):
    type: Literal["encounter"] = "encounter"
    encounter: EncounterEvent


class AnchorMessage(WireModel):
    type: Literal["anchor"] = "anchor"
    anchor: BuildingAnchor
    deleted: bool = False


class UserForgottenMessage(WireModel):
    """An operator made the server forget a user (``DELETE .../users/{user_id}``): drop it from the view."""

    type: Literal["user_forgotten"] = "user_forgotten"
    user_id: Identifier


class ZoneMessage(WireModel):
    """A user entered a zone, left it, or has stayed in it for the zone's dwell time
    (``schemas.zones.WebhookPayload`` is its webhook body)."""

    type: Literal["zone"] = "zone"
    zone_id: Identifier
    user_id: Identifier
    kind: ZoneKind
    t_ms: TimeMs
    probability: float = Field(ge=0.0, le=1.0, description="The share of its position inside the zone then.")


class HeartbeatMessage(WireModel):
    type: Literal["heartbeat"] = "heartbeat"
    t_ms: TimeMs
    dropped: int = Field(
        default=0, ge=0, description="Messages dropped for this subscriber because it was slow."
    )


LiveMessage = Annotated[
    PositionMessage
    | EncounterMessage
    | AnchorMessage
    | ZoneMessage
    | UserForgottenMessage
    | HeartbeatMessage,
    Field(discriminator="type"),
]
LIVE_MESSAGE_ADAPTER: TypeAdapter[LiveMessage] = TypeAdapter(LiveMessage)


class LiveBatch(WireModel):
    """With ``?batch=true`` each frame carries every message waiting for the subscriber (at most
    ``MAX_LIVE_BATCH``), in order: a dashboard of a busy building gets a few frames a second, not one per
    phone per second."""

    type: Literal["batch"] = "batch"
    messages: list[LiveMessage]


MAX_LIVE_BATCH = 1_000
