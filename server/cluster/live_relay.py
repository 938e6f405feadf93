"""Live messages over NATS: whoever changes a building (its worker's groups, a front's operator call)
publishes them on the building's live subject, and every front fans them out to its own dashboards."""

from __future__ import annotations

import asyncio

from nats.aio.client import Client

from schemas.live import LiveMessage
from server.cluster import messages
from server.cluster.names import live_subject
from server.live.broadcast import live_json


class LiveRelay:
    """A broadcaster sink (``server.live.broadcast.Sink``) that publishes to every front; call it from the
    event loop."""

    def __init__(self, connection: Client) -> None:
        self.connection = connection
        self._sending: set[asyncio.Task[None]] = set()  # held until sent: the loop keeps weak references

    def __call__(self, building_id: str, live: list[LiveMessage]) -> None:
        if not live:
            return
        data = messages.encode_live([live_json(m) for m in live])
        task = asyncio.get_running_loop().create_task(
            self.connection.publish(live_subject(building_id), data)
        )
        self._sending.add(task)
        task.add_done_callback(self._sending.discard)

    async def flush(self) -> None:
        """Wait for the messages being sent."""
        if self._sending:
            await asyncio.gather(*self._sending, return_exceptions=True)
