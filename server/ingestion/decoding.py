"""Bytes on the wire to a validated SensorBatch, or a ProblemError saying exactly what is wrong."""

from __future__ import annotations

import json

from pydantic import ValidationError

from schemas.sensors import SensorBatch
from server.errors import BodyTooLargeError, InvalidInputError, MalformedBodyError


def decode_batch(body: bytes, max_bytes: int) -> SensorBatch:
    """Validate a posted batch. Size is checked before parsing, so an oversized body costs nothing."""
    if len(body) > max_bytes:
        raise BodyTooLargeError(len(body), max_bytes)
    if not body.strip():
        raise MalformedBodyError("the request body is empty; send a SensorBatch as JSON")
    try:
        return SensorBatch.model_validate_json(body)
    except ValidationError as error:
        if any(e["type"] == "json_invalid" for e in error.errors()):
            raise MalformedBodyError(_json_error_detail(body)) from None
        raise InvalidInputError.from_validation_error(error, title="Invalid sensor batch") from None


def _json_error_detail(body: bytes) -> str:
    try:
        json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        return f"the body is not valid JSON: {error}"
    return "the body is not valid JSON"
