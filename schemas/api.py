"""Request and response bodies of the REST API that are not sensor data, estimates or anchors."""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated, Literal

from pydantic import Field, TypeAdapter

from schemas.common import Identifier, UtcDatetime, WireModel
from schemas.estimates import EncounterEvent, Estimate


class KeyScope(StrEnum):
    OPERATOR = "operator"
    DEVICE = "device"
    DASHBOARD = "dashboard"


class DeviceKeyIn(WireModel):
    """A device key: it posts batches as this one device of the building."""

    scope: Literal[KeyScope.DEVICE]
    device_id: Identifier


class DashboardKeyIn(WireModel):
    """A dashboard key: it reads the building (positions, anchors, the live view), changes nothing."""

    scope: Literal[KeyScope.DASHBOARD]
    device_id: None = None


class BuildingOperatorKeyIn(WireModel):
    """A building operator key: it manages this one building (anchors, plans, keys, users)."""

    scope: Literal[KeyScope.OPERATOR]
    device_id: None = None


KeyCreateIn = Annotated[DeviceKeyIn | DashboardKeyIn | BuildingOperatorKeyIn, Field(discriminator="scope")]
"""An operator mints a key for its building, chosen by ``scope``: a device key names its device, the
others none. One model a scope, each with its scope as a constant: a generated client takes the same
string for each."""
KEY_CREATE_ADAPTER: TypeAdapter[DeviceKeyIn | DashboardKeyIn | BuildingOperatorKeyIn] = TypeAdapter(
    KeyCreateIn
)


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
    created_at: UtcDatetime
    last_used_at: UtcDatetime | None = Field(
        default=None, description="To the minute; written every few seconds, not on every request."
    )
    revoked_at: UtcDatetime | None = None


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


class DevicePosition(WireModel):
    """A device's own view (``GET .../devices/{device}/position``): the user it posts as and, once that user
    is placed, its latest estimate. A phone shows itself from it after a reload."""

    device_id: Identifier
    user_id: Identifier | None = Field(description="None until the device has posted a batch.")
    estimate: Estimate | None = Field(
        default=None,
        description="The user's latest estimate; None until a position fix, a tag or a known anchor "
        "places it.",
    )


class FailingBuilding(WireModel):
    """A building in trouble lately, by an error of the server's (each logged): batches it could not apply
    (each refused alone with a 500, nothing of it kept), logged batches it could not apply again when it
    loaded after a crash, or a building that cannot be loaded at all (its requests answer 503)."""

    building_id: str
    failed_batches: int = Field(description="Batches refused since the building was loaded.")
    unreplayed_batches: int = Field(
        default=0,
        description="Acknowledged batches its last load could not apply again: it came back without them.",
    )
    failed_loads: int = Field(
        default=0,
        description="Attempts to load it that failed in a row; while nonzero its requests answer 503, and "
        "the next request after Retry-After tries again.",
    )
    last_failure_ms: int = Field(description="When the latest failure was (server time, epoch ms).")


class Health(WireModel):
    status: Literal["ok", "degraded"] = Field(
        default="ok",
        description="degraded while a building cannot be loaded, or has failed a batch in the last five "
        "minutes, or while the data directory's disk has less free space than CROWDSLAM_MIN_FREE_DISK_GB.",
    )
    database: str
    buildings_loaded: int
    failing_buildings: list[FailingBuilding] = Field(default_factory=list)
    disk_free_bytes: int = Field(ge=0, description="Free space on the data directory's disk.")
    low_disk: bool = Field(description="Less free space than CROWDSLAM_MIN_FREE_DISK_GB.")
