"""Dashboards subscribe to a building's live envelope: positions, encounters, anchor updates."""

from __future__ import annotations

import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from schemas.live import HeartbeatMessage
from server.api.deps import token_principal
from server.errors import ProblemError
from server.live.broadcast import Chunk, live_json
from server.state import AppState
from server.store import repositories as repo

router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["live"])


async def refuse(websocket: WebSocket, code: int, reason: str) -> None:
    """Accept, then close with the documented code and reason: a socket closed before it is accepted reaches
    the client as a bare HTTP 403, without either."""
    await websocket.accept()
    # a close frame's reason is at most 123 bytes of UTF-8
    await websocket.close(code=code, reason=reason.encode()[:120].decode(errors="ignore"))


HEARTBEAT_S = 10.0


@router.websocket("/live")
async def live(websocket: WebSocket, building_id: str, token: str | None = None, batch: bool = False) -> None:
    """``?token=<dashboard or operator key>``. Each text frame is one LiveMessage (JSON, union on ``type``);
    a heartbeat every 10 s reports messages dropped because this subscriber was slow. With ``&batch=true``
    each frame is a ``LiveBatch`` of every message waiting (for busy buildings)."""
    state: AppState = websocket.app.state.crowdslam
    try:
        caller = await token_principal(state, token)
        caller.require_reader(building_id)
    except ProblemError as exc:
        await refuse(websocket, 4401 if exc.status == 401 else 4403, exc.detail)
        return
    with state.sessions() as session:
        if repo.get_building(session, building_id) is None:
            await refuse(websocket, 4404, f"no building {building_id!r}")
            return
    open_now = state.live_sockets.get(caller.key_id, 0)
    if open_now >= state.settings.max_live_sockets_per_key:
        await refuse(websocket, 4429, f"this key holds {open_now} live sockets already, the most allowed")
        return
    state.live_sockets[caller.key_id] = open_now + 1
    try:
        await _serve(websocket, state, building_id, batch)
    finally:
        left = state.live_sockets.pop(caller.key_id, 1) - 1
        if left > 0:
            state.live_sockets[caller.key_id] = left


async def _serve(websocket: WebSocket, state: AppState, building_id: str, batch: bool) -> None:
    await websocket.accept()
    sub = state.broadcaster.subscribe(building_id)
    reported = 0
    try:
        while True:
            chunks = await sub.next(HEARTBEAT_S)
            if not chunks:
                heartbeat = HeartbeatMessage(t_ms=int(time.time() * 1000), dropped=sub.dropped - reported)
                reported = sub.dropped
                text = live_json(heartbeat)
                chunks = [Chunk([text], text)]
            if batch:
                await websocket.send_text(
                    '{"type":"batch","messages":[' + ",".join(c.joined for c in chunks) + "]}"
                )
                continue
            for chunk in chunks:
                for text in chunk.texts:
                    await websocket.send_text(text)
    except (WebSocketDisconnect, RuntimeError):
        return
    finally:
        state.broadcaster.unsubscribe(sub)
