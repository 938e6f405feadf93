"""Shared wire types: identifiers, timestamps, units and the limits every model enforces.

Conventions for everything that crosses the wire (REST, WebSocket, MCAP channels):
- Times are integer Unix epoch milliseconds (UTC), field names end in ``_ms``. Android sensor events carry
  nanoseconds since boot; the client converts them to wall-clock milliseconds before sending.
- Distances are metres (``_m``), angles radians (``_rad``), radio power dBm (``_dbm``), pressure hPa.
- Positions are in the building's local frame: x east, y north, metres, origin and rotation given by the
  building's geo-reference.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, GetCoreSchemaHandler, StringConstraints
from pydantic_core import CoreSchema

# Earliest and latest accepted timestamp: 2000-01-01 and 2100-01-01. A clock in seconds instead of
# milliseconds, or in nanoseconds since boot, falls outside and is rejected with a clear message.
MIN_TIME_MS = 946_684_800_000
MAX_TIME_MS = 4_102_444_800_000

Identifier = Annotated[
    str,
    StringConstraints(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9._:-]*$"),
]
"""Client-chosen identifier: 1-64 characters, letters, digits and ``._:-``, not starting with punctuation."""

TimeMs = Annotated[
    int,
    Field(
        ge=MIN_TIME_MS,
        le=MAX_TIME_MS,
        description="Unix epoch time in milliseconds (UTC).",
        examples=[1_796_559_880_000],
    ),
]


def _utc(value: datetime) -> datetime:
    """A time without an offset is UTC (the store keeps UTC; SQLite drops the offset)."""
    return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


UtcDatetime = Annotated[
    datetime,
    AfterValidator(_utc),
    Field(
        description="RFC 3339 date-time in UTC, e.g. 2026-12-06T12:24:40Z.", examples=["2026-12-06T12:24:40Z"]
    ),
]
"""A wall-clock instant on the wire: always RFC 3339 with its offset, in UTC (``Z``)."""

RssiDbm = Annotated[float, Field(ge=-120.0, le=0.0, description="Received signal strength in dBm.")]
TxPowerDbm = Annotated[float, Field(ge=-120.0, le=20.0, description="Transmit power in dBm.")]


_EXACT_JSON_TYPES = ("int", "float", "bool")


def _exact_json_types(schema: Any) -> None:
    """Numbers and booleans as the published JSON Schema reads them, everywhere in a core schema: strict, so
    that ``false`` or ``"1"`` is not taken for a number, nor ``"yes"`` or ``1`` for a boolean, as pydantic's
    lax mode would. Checked in pydantic's core: a second of IMU samples is thousands of numbers."""
    if isinstance(schema, list):
        for item in schema:
            _exact_json_types(item)
    elif isinstance(schema, dict):
        if schema.get("type") in _EXACT_JSON_TYPES:
            schema["strict"] = True
        for value in schema.values():
            _exact_json_types(value)


class WireModel(BaseModel):
    """Base of every wire model: unknown fields are errors, numbers must be finite, and a value of the wrong
    JSON type is refused rather than converted."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    @classmethod
    def __get_pydantic_core_schema__(
        cls, source: type[BaseModel], handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        schema = handler(source)
        _exact_json_types(schema)
        return schema


def _strictly_increasing(values: list[int]) -> list[int]:
    for i in range(1, len(values)):
        if values[i] <= values[i - 1]:
            raise ValueError(
                f"timestamps must be strictly increasing within a stream: t_ms[{i}]={values[i]} "
                f"follows t_ms[{i - 1}]={values[i - 1]}"
            )
    return values


IncreasingTimes = Annotated[list[TimeMs], AfterValidator(_strictly_increasing)]


def check_covariance(cov: list[list[float]]) -> list[list[float]]:
    """A 2x2 covariance must be symmetric positive semi-definite (tolerance for rounding)."""
    if len(cov) != 2 or any(len(row) != 2 for row in cov):
        raise ValueError("covariance must be a 2x2 matrix [[xx, xy], [xy, yy]]")
    (xx, xy), (yx, yy) = cov
    if not math.isclose(xy, yx, rel_tol=1e-9, abs_tol=1e-9):
        raise ValueError(f"covariance must be symmetric, got xy={xy} and yx={yx}")
    if xx < 0 or yy < 0 or xx * yy - xy * xy < -1e-9 * max(1.0, xx * yy):
        raise ValueError("covariance must be positive semi-definite")
    return cov


Covariance2 = Annotated[
    list[list[float]],
    AfterValidator(check_covariance),
    Field(
        description="2x2 position covariance in m^2, [[xx, xy], [xy, yy]]",
        examples=[[[0.64, 0.05], [0.05, 0.81]]],
    ),
]


MAX_COORDINATE_M = 100_000.0
"""100 km from the building's origin: beyond any building and its surroundings. A coordinate past it is
refused (422) before anything is touched: a fix at 1e160 m had made its user's filter overflow."""

Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]


class Position(WireModel):
    """A point in the building's local frame (x east, y north), within ``MAX_COORDINATE_M`` of its origin."""

    x_m: Coordinate
    y_m: Coordinate


def wire_config(example: dict[str, Any]) -> ConfigDict:
    """The WireModel config plus one example for the model's JSON Schema and OpenAPI docs."""
    return ConfigDict(
        extra="forbid", allow_inf_nan=False, frozen=True, json_schema_extra={"examples": [example]}
    )
