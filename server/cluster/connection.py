"""A cluster process's connection to NATS: it reconnects for as long as it runs (a NATS restart is an outage
to ride out, not a reason to stop), and says so in the log."""

from __future__ import annotations

import asyncio
import logging

import nats
from nats.aio.client import Client

logger = logging.getLogger(__name__)

RECONNECT_WAIT_S = 0.5
FIRST_CONNECT_S = 60.0
"""How long a starting process waits for NATS (started together, NATS may come up a little later)."""


class NatsUnreachableError(RuntimeError):
    pass


async def connect(url: str, name: str) -> Client:
    """Connected to the cluster's NATS at ``url`` (comma-separated for several servers)."""

    async def disconnected() -> None:
        logger.warning("%s: disconnected from NATS; reconnecting", name)

    async def reconnected() -> None:
        logger.warning("%s: reconnected to NATS", name)

    async def error(exc: Exception) -> None:
        logger.warning("%s: NATS: %r", name, exc)

    servers = [s.strip() for s in url.split(",") if s.strip()]
    try:
        connecting = nats.connect(
            servers=servers,
            name=name,
            connect_timeout=5,
            allow_reconnect=True,
            max_reconnect_attempts=-1,
            reconnect_time_wait=RECONNECT_WAIT_S,
            disconnected_cb=disconnected,
            reconnected_cb=reconnected,
            error_cb=error,
        )
        return await asyncio.wait_for(connecting, FIRST_CONNECT_S)
    except Exception as exc:
        raise NatsUnreachableError(f"cannot connect to NATS at {url}: {exc!r}") from exc
