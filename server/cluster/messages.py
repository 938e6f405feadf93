"""What the cluster's processes send each other over NATS, in one place. Batches, receipts and calls are
pickled, as between a front and a building's process (``server.buildings.process``): NATS is private to the
cluster, like its PostgreSQL, and must not be reachable by clients (docs/operations.md). Live messages go as
the JSON texts dashboards receive, a line each."""

from __future__ import annotations

import pickle
from typing import Any

from server.buildings.calls import Call
from server.buildings.submissions import BatchFields, transportable


def encode_stream_batch(reply_to: str, building_created: str, fields: BatchFields) -> bytes:
    """A batch in the stream: where its receipt goes, when its building was created (the stream may outlive a
    database, and a building its id: a worker applies only batches posted to the building it holds), and
    the batch as the front converted it."""
    return pickle.dumps((reply_to, building_created, fields), protocol=pickle.HIGHEST_PROTOCOL)


def decode_stream_batch(data: bytes) -> tuple[str, str, BatchFields]:
    reply_to, building_created, fields = pickle.loads(data)
    return str(reply_to), str(building_created), fields


def encode_answer(value: object) -> bytes:
    """A receipt (its JSON bytes), a call's value, or the error either raised (a ProblemError as it is, any
    other error as a RuntimeError naming it: the front answers 500 and logs it)."""
    if isinstance(value, Exception):
        return pickle.dumps((False, transportable(value)), protocol=pickle.HIGHEST_PROTOCOL)
    return pickle.dumps((True, value), protocol=pickle.HIGHEST_PROTOCOL)


def decode_answer(data: bytes) -> Any:
    """The answer's value; raises the error it carries."""
    ok, value = pickle.loads(data)
    if not ok:
        raise value
    return value


def encode_call(call: Call[Any]) -> bytes:
    return pickle.dumps(call, protocol=pickle.HIGHEST_PROTOCOL)


def decode_call(data: bytes) -> Call[Any]:
    """A building call (``server.buildings.calls``); ``TypeError`` for anything else."""
    call = pickle.loads(data)
    if not isinstance(call, Call):
        raise TypeError(f"not a building call: {type(call).__name__}")
    return call


def encode_live(texts: list[str]) -> bytes:
    """Live messages' JSON texts (compact JSON has no raw newline)."""
    return "\n".join(texts).encode()


def decode_live(data: bytes) -> list[str]:
    return data.decode().split("\n") if data else []
