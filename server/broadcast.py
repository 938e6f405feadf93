"""Live fan-out of a building's events to its WebSocket subscribers. A slow subscriber never slows the
building: its bounded queue drops the oldest message and the next heartbeat says how many it lost."""

from __future__ import annotations

import asyncio
import logging
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field

from schemas.live import LIVE_MESSAGE_ADAPTER, LiveMessage

QUEUE_SIZE = 2_000
Sink = Callable[[str, list[LiveMessage]], None]
"""Something else that sees every building's messages (the Foxglove live server)."""
log = logging.getLogger(__name__)


@dataclass(eq=False)
class Subscription:
    building_id: str
    queue: asyncio.Queue[str] = field(default_factory=lambda: asyncio.Queue(maxsize=QUEUE_SIZE))
    """Messages as JSON text, serialised once for every subscriber."""
    dropped: int = 0

    def offer(self, message: str) -> None:
        while True:
            try:
                self.queue.put_nowait(message)
                return
            except asyncio.QueueFull:
                self.queue.get_nowait()
                self.dropped += 1


class Broadcaster:
    """Call from the event loop only."""

    def __init__(self) -> None:
        self._subs: dict[str, set[Subscription]] = defaultdict(set)
        self._sinks: list[Sink] = []
        self.published = 0
        self.sink_errors = 0

    def add_sink(self, sink: Sink) -> None:
        self._sinks.append(sink)

    def subscribe(self, building_id: str) -> Subscription:
        sub = Subscription(building_id)
        self._subs[building_id].add(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        self._subs[sub.building_id].discard(sub)

    def publish(self, building_id: str, messages: list[LiveMessage]) -> None:
        self._to_sinks(building_id, messages)
        if self._subs.get(building_id):
            self._offer(building_id, [LIVE_MESSAGE_ADAPTER.dump_json(m).decode() for m in messages])

    def publish_texts(self, building_id: str, texts: list[str]) -> None:
        """Messages a building's process serialised (``publish`` without serialising again); sinks, which
        need the messages themselves, get them parsed back only when there are sinks."""
        if self._sinks and texts:
            self._to_sinks(building_id, [LIVE_MESSAGE_ADAPTER.validate_json(t) for t in texts])
        self._offer(building_id, texts)

    def _to_sinks(self, building_id: str, messages: list[LiveMessage]) -> None:
        for sink in self._sinks:
            try:
                sink(building_id, messages)
            except Exception:  # a viewer's trouble must never reach ingestion: counted and logged
                self.sink_errors += 1
                log.exception("live sink failed on %d messages of %s", len(messages), building_id)

    def _offer(self, building_id: str, texts: list[str]) -> None:
        """Each text to every subscriber of the building (serialised once for all of them)."""
        subs = self._subs.get(building_id)
        if not subs:
            return
        for text in texts:
            for sub in subs:
                sub.offer(text)
        self.published += len(texts)

    def subscribers(self, building_id: str | None = None) -> int:
        if building_id is None:
            return sum(len(s) for s in self._subs.values())
        return len(self._subs.get(building_id, ()))

    def queue_depths(self) -> list[int]:
        return [sub.queue.qsize() for subs in self._subs.values() for sub in subs]
