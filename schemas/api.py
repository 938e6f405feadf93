"""Request and response bodies of the REST API that are not sensor data, estimates or anchors."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Literal, Self

from pydantic import Field, model_validator

from schemas.common import Identifier, WireModel
from schemas.estimates import EncounterEvent, Estimate


class KeyScope(StrEnum):
    OPERATOR = "operator"
    DEVICE = "device"
    DASHBOARD = "dashboard"


class KeyCreateIn(WireModel):
    """An operator mints a key for its building: a device key posts as one device, a dashboard key reads."""

    scope: KeyScope
    device_id: Identifier | None = None

    @model_validator(mode="after")
    def _device(self) -> Self:
        if (self.scope == KeyScope.DEVICE) != (self.device_id is not None):
            raise ValueError("device_id is required for a device key and only allowed for one")
        return self


class KeyCreated(WireModel):
    """The secret is shown once; the server keeps only its SHA-256."""

    key: str
    prefix: str
    scope: KeyScope
    building_id: Identifier | None = None
    device_id: Identifier | None = None


class KeyInfo(WireModel):
    """A key as operators list it: never its secret."""

    prefix: str
    scope: KeyScope
    building_id: Identifier | None = None
    device_id: Identifier | None = None
    created_at: datetime
    last_used_at: datetime | None = Field(
        default=None, description="To the minute; written every few seconds, not on every request."
    )
    revoked_at: datetime | None = None


class KeyIdentity(WireModel):
    """The key presented (``GET /v1/key``): what it may do, so a client shows only what it will be allowed."""

    scope: KeyScope
    building_id: Identifier | None = Field(default=None, description="None: a site-wide operator key.")
    device_id: Identifier | None = None


class BatchReceipt(WireModel):
    """The answer to a posted batch. ``status``: applied; duplicate (this batch id was accepted before and
    nothing changed); late (its ``seq`` is not after the last applied one: recorded, not applied, counted)."""

    batch_id: Identifier
    status: Literal["applied", "duplicate", "late"]
    duplicate: bool
    tracking: bool = Field(description="False until the user's first position fix starts its filter.")
    estimate: Estimate | None = None
    encounters: list[EncounterEvent] = Field(default_factory=list)
    warnings: list[str] = Field(
        default_factory=list, description="Parts of the batch that were skipped, and why."
    )


class FailingBuilding(WireModel):
    """A building some of whose batches could not be applied lately (each refused alone, nothing kept)."""

    building_id: str
    failed_batches: int = Field(description="Batches refused since the building was loaded.")
    last_failure_ms: int = Field(description="When the latest was refused (server time, epoch ms).")


class Health(WireModel):
    status: Literal["ok", "degraded"] = Field(
        default="ok", description="degraded while a building has refused a batch in the last five minutes."
    )
    database: str
    buildings_loaded: int
    failing_buildings: list[FailingBuilding] = Field(default_factory=list)
