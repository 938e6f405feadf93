"""Limits every request meets before any work is done: its body's size, checked on ``Content-Length`` and
again while the body streams in, before the route reads it and before the caller's key is looked up.

An anonymous caller could otherwise make the server hold a body of any size in memory only to answer 401
(a 400 MiB ``POST /v1/buildings`` had grown the server by 1.1 GB). The batch route reads its body itself
under its own limit (``CROWDSLAM_MAX_BATCH_BYTES``, ``server.api.batches``); every other route is held to
``CROWDSLAM_MAX_REQUEST_BYTES``, but floor plans, held to ``CROWDSLAM_MAX_PLAN_BYTES``.
"""

from __future__ import annotations

import re

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.errors import BodyTooLargeError, MalformedBodyError, ProblemError, problem_response_parts

BATCHES_PATH = re.compile(r"/v1/buildings/([^/]+)/batches")
"""The batch route: read under its own limit by ``server.api.batches.serve_batch``."""
PLAN_PATH = re.compile(r"/v1/buildings/[^/]+/floors/[^/]+/plan")
"""Floor plans are larger than other requests (a mall floor's GeoJSON is ~0.1-0.3 MB)."""


class BodyLimit:
    """Pure ASGI middleware: 413 for a declared or streamed body over the limit, before the app reads it."""

    def __init__(self, app: ASGIApp, limit: int, plan_limit: int) -> None:
        self.app = app
        self.default_limit = limit
        self.plan_limit = plan_limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or BATCHES_PATH.fullmatch(scope["path"]):
            await self.app(scope, receive, send)
            return
        limit = self.plan_limit if PLAN_PATH.fullmatch(scope["path"]) else self.default_limit
        for name, value in scope["headers"]:
            if name == b"content-length":
                declared = value.decode("latin-1")
                if not declared.isdigit():
                    await _answer(send, MalformedBodyError("the Content-Length header is not a number"))
                    return
                if int(declared) > limit:
                    await _answer(send, BodyTooLargeError(int(declared), limit))
                    return
        received = 0
        started = answered = False

        async def limited_receive() -> Message:
            nonlocal received, answered
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    # answered here, and the route sees the client leave: nothing more is read or kept
                    if not started and not answered:
                        answered = True
                        await _answer(send, BodyTooLargeError(received, limit))
                    return {"type": "http.disconnect"}
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if answered:  # the route's own answer to the "disconnect" goes nowhere
                return
            started = started or message["type"] == "http.response.start"
            await send(message)

        await self.app(scope, limited_receive, guarded_send)


async def _answer(send: Send, error: ProblemError) -> None:
    status, body, headers = problem_response_parts(error.to_problem())
    await send_response(send, status, body, {**headers, "connection": "close"})  # the rest goes unread


async def send_response(send: Send, status: int, body: bytes, headers: dict[str, str]) -> None:
    """A whole response from a pure ASGI middleware: status, headers (with the length) and body."""
    raw = [(k.encode("latin-1"), v.encode("latin-1")) for k, v in headers.items()]
    raw.append((b"content-length", str(len(body)).encode("latin-1")))
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})
