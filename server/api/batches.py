"""Phones post sensor batches (REST or a WebSocket stream of the same schema)."""

from __future__ import annotations

import time
from typing import Any

from fastapi import APIRouter, Request, Response, WebSocket, WebSocketDisconnect

from schemas.api import BatchReceipt
from schemas.errors import Problem
from schemas.sensors import SensorBatch
from server.app import AppState
from server.auth import Principal
from server.batch_decoding import decode_batch
from server.deps import AUTHORIZATION_PARAMETER, principal, token_principal
from server.errors import BodyTooLargeError, InvalidInputError, ProblemError
from server.tracking import Submission

router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["batches"])

_BATCH_BODY: dict[str, Any] = {
    "parameters": [AUTHORIZATION_PARAMETER],
    "requestBody": {
        "required": True,
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/SensorBatch"}}},
    },
}


async def ingest(state: AppState, caller: Principal, building_id: str, body: bytes) -> BatchReceipt:
    """Validate, authorise, then hand the batch to its building. Nothing is touched before all checks pass."""
    caller.require_device(building_id, None)
    batch = decode_batch(body, state.settings.max_batch_bytes)
    if batch.building_id != building_id:
        raise InvalidInputError(
            f"the batch names building {batch.building_id!r} but was posted to building {building_id!r}"
        )
    caller.require_device(building_id, batch.device_id)
    worker = await state.tracking.worker(building_id)
    return await worker.submit(Submission(batch, body, time.time_ns()))


@router.post(
    "/batches",
    response_model=BatchReceipt,
    openapi_extra=_BATCH_BODY,
    responses={
        400: {"model": Problem},
        404: {"model": Problem},
        413: {"model": Problem},
        422: {"model": Problem},
    },
)
async def post_batch(building_id: str, request: Request) -> Response:
    """Post one sensor batch (device key). A retried batch (same ``batch_id``) answers ``duplicate`` and
    changes nothing; a batch whose ``seq`` is not after the device's last applied one answers ``late``."""
    # The hottest route reads its state and key itself: FastAPI's dependency resolution (header, cookie and
    # query parsing, a sub-dependency per argument) cost more than the batch's validation under load.
    state: AppState = request.app.state.crowdslam
    caller = await principal(state, request.headers.get("authorization"))
    length = request.headers.get("content-length")
    limit = state.settings.max_batch_bytes
    if length is not None and length.isdigit() and int(length) > limit:
        raise BodyTooLargeError(int(length), limit)
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > limit:
            raise BodyTooLargeError(len(body), limit)
    receipt = await ingest(state, caller, building_id, bytes(body))
    # already a validated model: serialise it directly (response_model still documents it)
    return Response(receipt.model_dump_json(), media_type="application/json")


@router.websocket("/stream")
async def stream_batches(websocket: WebSocket, building_id: str, token: str | None = None) -> None:
    """Phones may stream batches over ``?token=<device key>``: each text frame is a SensorBatch, each answer
    a BatchReceipt or Problem, in order. The key is checked again for every frame through the key cache,
    so a revoked key's stream is closed (4401) within ``CROWDSLAM_KEY_CACHE_S``."""
    state: AppState = websocket.app.state.crowdslam
    try:
        caller = await token_principal(state, token)
    except ProblemError:
        await websocket.close(code=4401, reason="unknown or missing key")
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
                await websocket.send_text(receipt.model_dump_json())
            except ProblemError as exc:
                await websocket.send_text(exc.to_problem().model_dump_json())
    except WebSocketDisconnect:
        return


__all__ = ["SensorBatch", "router"]
