"""Dashboards subscribe to a building's live envelope: positions, encounters, anchor updates."""

from __future__ import annotations

import asyncio
import contextlib
import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from schemas.live import HeartbeatMessage
from server.api.deps import token_principal
from server.errors import ProblemError
from server.live.broadcast import Chunk, Subscription, live_json
from server.state import AppState
from server.store import repositories as repo

router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["live"])


SUBPROTOCOL = "crowdslam.live"
"""The subprotocol a browser offers, beside ``bearer.<key>``, to authenticate without a query string."""
BEARER_PREFIX = "bearer."


def offered_key(websocket: WebSocket) -> str | None:
    """The key offered as the subprotocol ``bearer.<key>`` (a browser cannot set a WebSocket's headers, and
    a query string lands in access logs)."""
    for offered in websocket.scope.get("subprotocols", []):
        if offered.startswith(BEARER_PREFIX):
            return str(offered[len(BEARER_PREFIX) :])
    return None


def chosen_subprotocol(websocket: WebSocket) -> str | None:
    """The subprotocol to accept: a browser that offered some fails the handshake unless one is chosen."""
    return SUBPROTOCOL if SUBPROTOCOL in websocket.scope.get("subprotocols", []) else None


async def refuse(websocket: WebSocket, code: int, reason: str) -> None:
    """Accept, then close with the documented code and reason: a socket closed before it is accepted reaches
    the client as a bare HTTP 403, without either."""
    await websocket.accept(subprotocol=chosen_subprotocol(websocket))
    # a close frame's reason is at most 123 bytes of UTF-8
    await websocket.close(code=code, reason=reason.encode()[:120].decode(errors="ignore"))


HEARTBEAT_S = 10.0
KEY_RECHECK_S = 2.0
"""How often an open socket's key is checked again (through the key cache): a revoked key's sockets close
with 4401 within this time on the server that revoked it, within ``CROWDSLAM_KEY_CACHE_S`` on others."""


@router.websocket("/live")
async def live(websocket: WebSocket, building_id: str, token: str | None = None, batch: bool = False) -> None:
    """A dashboard or operator key, as the subprotocols ``crowdslam.live, bearer.<key>`` (browsers; no key
    in a URL that logs keep) or ``?token=<key>``. Each text frame is one LiveMessage (JSON, union on
    ``type``); a heartbeat every 10 s of quiet reports messages dropped because this subscriber was slow.
    With ``&batch=true`` each frame is a ``LiveBatch`` of every message waiting (for busy buildings). A key
    revoked while its socket is open closes it with 4401."""
    state: AppState = websocket.app.state.crowdslam
    token = offered_key(websocket) or token
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
        await _serve(websocket, state, building_id, batch, token)
    finally:
        left = state.live_sockets.pop(caller.key_id, 1) - 1
        if left > 0:
            state.live_sockets[caller.key_id] = left


async def _serve(
    websocket: WebSocket, state: AppState, building_id: str, batch: bool, token: str | None
) -> None:
    await websocket.accept(subprotocol=chosen_subprotocol(websocket))
    sub = state.broadcaster.subscribe(building_id)
    watcher = asyncio.create_task(_close_when_gone(websocket, sub))
    reported = 0
    sent_at = checked_at = time.monotonic()
    try:
        while True:
            chunks = await sub.next(KEY_RECHECK_S)
            if sub.closed:
                return
            now = time.monotonic()
            if now - checked_at >= KEY_RECHECK_S:
                checked_at = now
                try:
                    (await token_principal(state, token)).require_reader(building_id)
                except ProblemError as exc:
                    await websocket.close(code=4401 if exc.status == 401 else 4403, reason="key revoked")
                    return
            if not chunks:
                if now - sent_at < HEARTBEAT_S:
                    continue
                heartbeat = HeartbeatMessage(t_ms=int(time.time() * 1000), dropped=sub.dropped - reported)
                reported = sub.dropped
                text = live_json(heartbeat)
                chunks = [Chunk([text], text)]
            if batch:
                await websocket.send_text(
                    '{"type":"batch","messages":[' + ",".join(c.joined for c in chunks) + "]}"
                )
                sent_at = now
                continue
            for chunk in chunks:
                for text in chunk.texts:
                    await websocket.send_text(text)
            sent_at = now
    except (WebSocketDisconnect, RuntimeError):
        return
    finally:
        watcher.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await watcher
        state.broadcaster.unsubscribe(sub)


async def _close_when_gone(websocket: WebSocket, sub: Subscription) -> None:
    """Read the socket until the dashboard leaves, then close its subscription. Without a reader, a quiet
    building's closed socket would hold its subscriber and its slot in the key's socket limit until the next
    heartbeat failed to send (up to 10 s), and hold a server's shutdown as long. A live socket takes no
    messages: a client that sends one is closed with 1008 (``Settings.max_ws_frame_bytes`` bounds what the
    server reads of it)."""
    try:
        message = await websocket.receive()
        if message["type"] == "websocket.receive":
            await websocket.close(code=1008, reason="a live socket takes no messages")
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        sub.close()
