"""Zones: areas operators draw on a floor (a shop front, a ward, a gate), who is in them, their visits, and
the webhooks that tell a receiver of their entries, exits and dwells."""

from __future__ import annotations

from typing import Annotated, Any, Literal, Self

from pydantic import Field, HttpUrl, model_validator

from schemas.common import Identifier, TimeMs, WireModel, wire_config
from schemas.floor_plans import Point

MAX_ZONES = 500
"""Zones a building may hold."""
MAX_ZONE_VERTICES = 512
"""Positions a zone's outline may hold (a shop front needs five; a traced ward, dozens)."""
MAX_VISITS = 10_000
"""Visits one answer lists at most (``limit``)."""

ZoneKind = Literal["enter", "exit", "dwell"]
WebhookEvent = Literal["zone.enter", "zone.exit", "zone.dwell"]


class ZonePolygon(WireModel):
    """A GeoJSON Polygon (RFC 7946) in the building's local frame, metres: one closed ring, without holes."""

    type: Literal["Polygon"]
    coordinates: list[
        Annotated[
            list[Point],
            Field(
                min_length=4,
                max_length=MAX_ZONE_VERTICES + 1,
                description="A closed ring: the first position repeated last.",
            ),
        ]
    ] = Field(min_length=1, max_length=16, description="The outline: a zone has one ring and no holes.")

    @model_validator(mode="after")
    def _closed(self) -> Self:
        if len(self.coordinates) > 1:
            raise ValueError("a zone's polygon is one ring: holes are not supported (draw zones around them)")
        ring = self.coordinates[0]
        if ring[0] != ring[-1]:
            raise ValueError("a zone's ring must end at its first position")
        return self


ZONE_EXAMPLE: dict[str, Any] = {
    "floor": 0,
    "name": "Cafe front",
    "polygon": {"type": "Polygon", "coordinates": [[[10, 5], [18, 5], [18, 9], [10, 9], [10, 5]]]},
    "dwell_s": 300,
}


class ZoneIn(WireModel):
    """A zone as an operator draws it."""

    model_config = wire_config(ZONE_EXAMPLE)

    floor: int = Field(ge=-20, le=200, description="The floor's level (0 in a building without floors).")
    name: str = Field(min_length=1, max_length=128)
    polygon: ZonePolygon
    dwell_s: float | None = Field(
        default=None,
        gt=0.0,
        le=7 * 86_400.0,
        description="A dwell event fires once a user has been inside this long (none when null).",
    )


class Zone(ZoneIn):
    id: Identifier
    occupancy: int = Field(ge=0, description="Users inside now.")


class ZoneVisit(WireModel):
    """One user's stay in a zone: from its entry to its exit (``left_ms`` null: inside still)."""

    zone_id: Identifier
    user_id: Identifier
    entered_ms: TimeMs
    left_ms: TimeMs | None
    seconds: float | None = Field(description="How long it stayed (null while inside).")
    dwelled: bool = Field(description="Whether its dwell event fired.")


class ZoneOccupancy(WireModel):
    """Users inside each zone at ``at_ms``, from the stored visits."""

    at_ms: TimeMs
    zones: dict[str, int]


class WebhookPayload(WireModel):
    """The JSON body of a webhook delivery: a user entered a zone, left it, or has stayed in it for the
    zone's ``dwell_s``. ``id`` is the event's, the same in every delivery of it (a receiver that sees it
    twice, after a retry whose answer was lost, drops the second)."""

    id: str = Field(min_length=1, max_length=64)
    event: WebhookEvent
    building_id: Identifier
    zone_id: Identifier
    user_id: Identifier
    t_ms: TimeMs
    probability: float = Field(
        ge=0.0,
        le=1.0,
        description="The share of the user's position inside the zone then (0 when the server stopped "
        "tracking it).",
    )


WEBHOOK_EXAMPLE: dict[str, Any] = {
    "url": "https://apps.example.com/crowdslam",
    "secret": "a long random string shared with the receiver",
    "events": ["zone.enter", "zone.exit"],
}


class WebhookIn(WireModel):
    """Where to POST zone events. Each delivery is signed: ``X-Crowdslam-Signature: sha256=<hex HMAC-SHA256
    of the body with the secret>``."""

    model_config = wire_config(WEBHOOK_EXAMPLE)

    url: HttpUrl = Field(description="http or https; no credentials in it.")
    secret: str = Field(min_length=16, max_length=256, description="Signs each delivery; never shown again.")
    events: list[WebhookEvent] = Field(min_length=1, max_length=3)

    @model_validator(mode="after")
    def _plain(self) -> Self:
        if self.url.scheme not in ("http", "https"):
            raise ValueError("a webhook's url is http or https")
        if self.url.username or self.url.password:
            raise ValueError("a webhook's url carries no credentials: the signature authenticates it")
        if len(set(self.events)) != len(self.events):
            raise ValueError("each event once")
        return self


class Webhook(WireModel):
    id: Identifier
    url: str
    events: list[WebhookEvent]
    suspended: bool = Field(
        description="After a delivery gave up, the webhook takes no new events until it is PUT again."
    )


class WebhookDelivery(WireModel):
    """One event's delivery to a webhook: tried in order with the webhook's other deliveries, again with
    backoff after a failure, until the receiver answers 2xx or the tries run out."""

    id: int
    webhook_id: Identifier
    event: WebhookEvent
    body: str = Field(description="The JSON body as signed and sent.")
    created_ms: TimeMs
    attempts: int = Field(ge=0)
    status: Literal["pending", "delivered", "gave_up"]
    http_status: int | None = Field(description="The receiver's answer to the last try, if it answered.")
    error: str | None = Field(description="Why the last try failed.")
    next_attempt_ms: TimeMs | None
    delivered_ms: TimeMs | None


MAX_WEBHOOKS = 20
"""Webhooks a building may hold."""
