"""Bytes on the wire to a validated SensorBatch, or a ProblemError saying exactly what is wrong."""

from __future__ import annotations

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
        invalid = [e for e in error.errors() if e["type"] == "json_invalid"]
        if invalid:  # the parser's own words: where it stopped, or that nesting passed its depth limit
            raise MalformedBodyError(f"the body is not valid JSON: {invalid[0]['msg']}") from None
        raise InvalidInputError.from_validation_error(error, title="Invalid sensor batch") from None
