"""The one error body of the API (RFC 9457 problem details)."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from schemas.common import WireModel, wire_config


class FieldProblem(WireModel):
    """One offending input field."""

    loc: str = Field(
        description="Path to the field, e.g. 'wifi_scans.0.aps.3.rssi_dbm'.", examples=["steps.0.length_m"]
    )
    msg: str
    type: str = Field(description="Machine-readable error kind, e.g. 'less_than_equal'.")


PROBLEM_EXAMPLE: dict[str, Any] = {
    "type": "about:blank",
    "title": "Invalid sensor batch",
    "status": 422,
    "detail": "1 field is invalid",
    "errors": [
        {
            "loc": "wifi_scans.0.aps.0.rssi_dbm",
            "msg": "Input should be less than or equal to 0",
            "type": "less_than_equal",
        }
    ],
}


class Problem(WireModel):
    model_config = wire_config(PROBLEM_EXAMPLE)

    type: str = "about:blank"
    title: str
    status: int = Field(ge=400, le=599)
    detail: str | None = None
    errors: list[FieldProblem] = Field(default_factory=list)
