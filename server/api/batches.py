"""Phones post sensor batches (REST or a WebSocket stream of the same schema)."""

from __future__ import annotations

import logging
import time
import zlib
from typing import Any

from fastapi import APIRouter, Request, Response, WebSocket, WebSocketDisconnect
from starlette.types import Receive, Scope, Send

from schemas.api import BatchReceipt
from schemas.sensors import SensorBatch
from server.api.contract import PROBLEMS, SECURITY_SCHEME, problems
from server.api.deps import principal, token_principal
from server.api.limits import send_response
from server.api.links import BUILDING, SAME_BUILDING, link
from server.api.live import refuse
from server.auth import Principal
from server.buildings.submissions import Submission
from server.errors import (
    BodyTooLargeError,
    InvalidInputError,
    MalformedBodyError,
    ProblemError,
    TooManyRequestsError,
    UnexpectedError,
    UnsupportedEncodingError,
    problem_response_parts,
)
from server.ingestion.decoding import decode_batch
from server.rate_limit import retry_after_header
from server.state import AppState

logger = logging.getLogger(__name__)
router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["batches"])

_BATCH_BODY: dict[str, Any] = {
    "security": [{SECURITY_SCHEME: []}],
    "requestBody": {
        "required": True,
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/SensorBatch"}}},
    },
}


async def ingest(state: AppState, caller: Principal, building_id: str, body: bytes) -> bytes:
    """Validate, authorise, then hand the batch to its building; its ``BatchReceipt`` as JSON. Nothing is
    touched before all checks pass."""
    caller.require_device(building_id, None)
    wait_s = state.rate.take(caller.key_id)
    if wait_s > 0:
        raise TooManyRequestsError(
            f"this device key posts more than {state.settings.device_rate_per_s:g} batches a second; "
            f"retry in {wait_s:.1f} s",
            wait_s,
        )
    batch = decode_batch(body, state.settings.max_batch_bytes)
    if batch.building_id != building_id:
        raise InvalidInputError(
            f"the batch names building {batch.building_id!r} but was posted to building {building_id!r}"
        )
    caller.require_device(building_id, batch.device_id)
    received_ns = time.time_ns()
    submission = Submission.of(batch, body, received_ns)  # the front's conversion: its header has the span
    span = submission.header.span_ms
    if span is not None and span[1] > received_ns // 1_000_000 + MAX_CLOCK_AHEAD_MS:
        ahead_s = (span[1] - received_ns // 1_000_000) / 1000
        raise InvalidInputError(
            f"the batch's latest time is {ahead_s:.0f} s ahead of the server's clock; at most "
            f"{MAX_CLOCK_AHEAD_MS // 1000} s are accepted (is the phone's clock set?)"
        )
    building = await state.tracking.handle(building_id)
    return await building.submit(submission)


MAX_CLOCK_AHEAD_MS = 300_000
"""A batch timed more than five minutes ahead of the server's clock is refused: applied, it would set its
user's timeline in the future and every later batch would look out of order."""

_WANTED_HEADERS = (b"authorization", b"content-length", b"content-encoding")


def _decoded(body: bytes, encoding: str | None, limit: int) -> bytes:
    """The body as JSON bytes: as sent, or gunzipped (``Content-Encoding: gzip``, which a phone on a slow
    link may use). The decompressed size is held to ``limit`` as it is produced (a small body that inflates
    without end is refused, 413, before it takes the memory); a body that is not gzip is 400."""
    if encoding is None or encoding.strip().lower() in ("", "identity"):
        return body
    if encoding.strip().lower() != "gzip":
        raise UnsupportedEncodingError(encoding)
    inflate = zlib.decompressobj(wbits=31)  # a gzip header and trailer
    try:
        out = inflate.decompress(body, limit + 1)
    except zlib.error as exc:
        raise MalformedBodyError(f"the body is not gzip ({exc}), though Content-Encoding says so") from None
    if len(out) > limit:
        raise BodyTooLargeError(len(out), limit, "decompressed")
    if not inflate.eof or inflate.unused_data:
        raise MalformedBodyError("the gzip body is cut short, or has data after its end")
    return out


async def _read_body(receive: Receive, limit: int) -> bytes | None:
    """The request body, refused as soon as it exceeds ``limit`` bytes; None if the client left."""
    body = bytearray()
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            return None
        body += message.get("body", b"")
        if len(body) > limit:
            raise BodyTooLargeError(len(body), limit)
        if not message.get("more_body", False):
            return bytes(body)


async def _answer_batch(
    state: AppState,
    building_id: str,
    authorization: str | None,
    length: str | None,
    receive: Receive,
    encoding: str | None = None,
) -> tuple[int, bytes, dict[str, str]] | None:
    """The whole POST /batches exchange: key, size, body, ingestion; a ProblemError becomes its Problem.
    None when the client left before sending its body."""
    # The hottest route reads its state and key itself: FastAPI's dependency resolution (header, cookie and
    # query parsing, a sub-dependency per argument) cost more than the batch's validation under load.
    try:
        caller = await principal(state, authorization)
        limit = state.settings.max_batch_bytes
        if length is not None and length.isdigit() and int(length) > limit:
            raise BodyTooLargeError(int(length), limit)
        body = await _read_body(receive, limit)
        if body is None:
            return None
        receipt = await ingest(state, caller, building_id, _decoded(body, encoding, limit))
    except ProblemError as exc:
        status, problem, headers = problem_response_parts(exc.to_problem())
        if exc.retry_after_s is not None:
            headers["retry-after"] = retry_after_header(exc.retry_after_s)
        return status, problem, headers
    # serialised by the building (the route's response_model documents it)
    return 200, receipt, {"content-type": "application/json"}


async def serve_batch(state: AppState, building_id: str, scope: Scope, receive: Receive, send: Send) -> None:
    """The whole POST /v1/buildings/{id}/batches as pure ASGI, the request every phone makes every second,
    taken by the app before its middleware, router and request objects (``server.app.CrowdslamApp``: under
    load they cost as much as validating the batch). The route below documents the operation and answers
    identically (``_answer_batch``) where this is off. An error no Problem names answers as the app's own
    handler does: 500, logged, without its text."""
    try:
        headers = {name: value for name, value in scope["headers"] if name in _WANTED_HEADERS}
        authorization = headers.get(b"authorization")
        length = headers.get(b"content-length")
        encoding = headers.get(b"content-encoding")
        answer = await _answer_batch(
            state,
            building_id,
            None if authorization is None else authorization.decode("latin-1"),
            None if length is None else length.decode("latin-1"),
            receive,
            None if encoding is None else encoding.decode("latin-1"),
        )
    except Exception:
        logger.exception("POST %s failed", scope["path"])
        answer = problem_response_parts(UnexpectedError().to_problem())
    if answer is not None:
        await send_response(send, *answer)


@router.post(
    "/batches",
    response_model=BatchReceipt,
    openapi_extra=_BATCH_BODY,
    responses={
        200: {
            "links": {
                "UserHistory": link(
                    "GET",
                    f"{BUILDING}/users/{{user_id}}/positions",
                    "The device's positions.",
                    building_id=SAME_BUILDING,
                    user_id="$request.body#/device_id",
                )
            }
        },
        **problems(
            400,
            (403, "A device key of another building or device, or a key that is not a device key."),
            404,
            (413, PROBLEMS[413] + " A gzip body counts decompressed too."),
            (415, "A Content-Encoding other than gzip or identity."),
            (
                422,
                PROBLEMS[422] + " Beyond the schema: the batch names the building it is posted to, and its "
                "latest time is at most five minutes ahead of the server's clock.",
            ),
            (
                429,
                "This device key posts faster than `CROWDSLAM_DEVICE_RATE_PER_S`: send again after "
                "`Retry-After` seconds.",
            ),
            500,
            503,
        ),
    },
)
async def post_batch(building_id: str, request: Request) -> Response:
    """Post one sensor batch (device key). A retried batch (same ``batch_id``) answers ``duplicate`` and
    changes nothing; a batch whose ``seq`` is not after the device's last applied one answers ``late``. The
    body may be gzip-compressed (``Content-Encoding: gzip``); its decompressed size counts against the
    batch limit."""
    answer = await _answer_batch(
        request.app.state.crowdslam,
        building_id,
        request.headers.get("authorization"),
        request.headers.get("content-length"),
        request.receive,
        request.headers.get("content-encoding"),
    )
    if answer is None:  # the client left: nobody reads this
        return Response(status_code=400)
    status, body, headers = answer
    return Response(body, status_code=status, headers=headers)


@router.websocket("/stream")
async def stream_batches(websocket: WebSocket, building_id: str, token: str | None = None) -> None:
    """Phones may stream batches over ``?token=<device key>``: each text frame is a SensorBatch, each answer
    a BatchReceipt or Problem, in order. The key is checked again for every frame through the key cache,
    so a revoked key's stream is closed (4401) within ``CROWDSLAM_KEY_CACHE_S``."""
    state: AppState = websocket.app.state.crowdslam
    try:
        caller = await token_principal(state, token)
    except ProblemError:
        await refuse(websocket, 4401, "unknown or missing key")
        return
    await websocket.accept()
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            raw = message.get("text")
            data = raw.encode() if raw is not None else (message.get("bytes") or b"")
            try:
                caller = await token_principal(state, token)
            except ProblemError as exc:
                await websocket.send_text(exc.to_problem().model_dump_json())
                await websocket.close(code=4401, reason="the key is unknown or revoked")
                return
            try:
                receipt = await ingest(state, caller, building_id, data)
                await websocket.send_text(receipt.decode())
            except ProblemError as exc:
                await websocket.send_text(exc.to_problem().model_dump_json())
    except WebSocketDisconnect:
        return


__all__ = ["SensorBatch", "router"]
