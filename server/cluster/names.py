"""Names in NATS: a token a subject or key may hold for a building, whatever its id, and the subjects the
cluster's processes talk on besides the batch stream."""

from __future__ import annotations


def building_token(building_id: str) -> str:
    """A building id as one subject token or key: ids may hold ``:`` (not allowed in a key) and ``.`` (a
    subject's separator), so the id's UTF-8 is written in hex (an id is at most 64 characters)."""
    return "b" + building_id.encode().hex()


def token_building(token: str) -> str:
    """``building_token``'s inverse; ValueError for a token it did not make."""
    try:
        if token.startswith("b"):
            return bytes.fromhex(token[1:]).decode()
    except ValueError:  # not hex, or not UTF-8
        pass
    raise ValueError(f"{token!r} is not a building token")


def live_subject(building_id: str) -> str:
    """Where a building's worker publishes its live messages, for every front's dashboards."""
    return f"crowdslam.live.{building_token(building_id)}"


LIVE_SUBJECTS = "crowdslam.live.*"


def calls_subject(building_id: str) -> str:
    """Where the worker owning a building answers operators' calls (anchor edits, plans, devices)."""
    return f"crowdslam.calls.{building_token(building_id)}"


def receipts_subject(front_id: str, request: int | None = None) -> str:
    """Where a front hears the receipts of the batches it published (one subject per request, so that the
    receipt needs no header: the request is the subject's last token); ``None``: all of them."""
    return f"crowdslam.receipts.{front_id}.{'*' if request is None else request}"
