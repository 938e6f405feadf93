"""Names in NATS for a building: a token a subject or key may hold, whatever the building's id."""

from __future__ import annotations


def building_token(building_id: str) -> str:
    """A building id as one subject token or key: ids may hold ``:`` (not allowed in a key) and ``.`` (a
    subject's separator), so the id's UTF-8 is written in hex (an id is at most 64 characters)."""
    return "b" + building_id.encode().hex()
