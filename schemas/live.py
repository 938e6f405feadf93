"""The live WebSocket envelope: one message per event, a discriminated union on ``type``."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, TypeAdapter

from schemas.anchors import BuildingAnchor
from schemas.common import TimeMs, WireModel
from schemas.estimates import EncounterEvent, Estimate


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


class HeartbeatMessage(WireModel):
    type: Literal["heartbeat"] = "heartbeat"
    t_ms: TimeMs
    dropped: int = Field(
        default=0, ge=0, description="Messages dropped for this subscriber because it was slow."
    )


LiveMessage = Annotated[
    PositionMessage | EncounterMessage | AnchorMessage | HeartbeatMessage, Field(discriminator="type")
]
LIVE_MESSAGE_ADAPTER: TypeAdapter[LiveMessage] = TypeAdapter(LiveMessage)
