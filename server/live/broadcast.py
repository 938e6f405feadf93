"""Live fan-out of a building's events to its WebSocket subscribers. A slow subscriber never slows the
building: its bounded queue drops the oldest messages and the next heartbeat says how many it lost.

A publish (one building group's messages) reaches each subscriber as one ``Chunk``: its messages'
JSON texts, and the same texts joined, built once for every subscriber, so that a batched frame
(``?batch=true``) is a join of a few chunks rather than of every message, and a busy building costs
each subscriber a queue entry per group rather than per phone."""

from __future__ import annotations

import asyncio
import logging
from collections import defaultdict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

from schemas.live import LIVE_MESSAGE_ADAPTER, MAX_LIVE_BATCH, LiveMessage

QUEUE_SIZE = 2_000
"""Messages a subscriber may have waiting; beyond it the oldest are dropped (whole chunks)."""
Sink = Callable[[str, list[LiveMessage]], None]
"""Something else that sees every building's messages (the Foxglove live server)."""
log = logging.getLogger(__name__)


class Chunk(NamedTuple):
    """Consecutive messages of one publish, at most ``MAX_LIVE_BATCH``."""

    texts: list[str]
    """One JSON text per message."""
    joined: str
    """The texts joined by commas: a piece of a ``LiveBatch`` frame's ``messages`` array."""


def live_json(message: LiveMessage) -> str:
    """A live message as its JSON text: what ``LIVE_MESSAGE_ADAPTER.dump_json`` gives, through the message's
    own model (each member of the union serialises its ``type`` first): the union's adapter took ~40 % longer
    to pick the member, once per position a second."""
    return message.model_dump_json()


def chunks_of(texts: list[str]) -> list[Chunk]:
    """``texts`` cut into chunks of at most ``MAX_LIVE_BATCH``, so that a frame of whole chunks stays
    within it."""
    return [
        Chunk(part, ",".join(part))
        for part in (texts[i : i + MAX_LIVE_BATCH] for i in range(0, len(texts), MAX_LIVE_BATCH))
    ]


@dataclass(eq=False)
class Subscription:
    building_id: str
    dropped: int = 0
    """Messages dropped because this subscriber was slow (never reset; the endpoint reports the change)."""
    queued: int = 0
    """Messages waiting."""
    closed: bool = False
    """Its socket closed: ``next`` returns at once, and the endpoint stops."""
    _chunks: deque[Chunk] = field(default_factory=deque)
    _ready: asyncio.Event = field(default_factory=asyncio.Event)

    def offer(self, chunk: Chunk) -> None:
        self._chunks.append(chunk)
        self.queued += len(chunk.texts)
        while self.queued > QUEUE_SIZE:
            oldest = self._chunks.popleft()
            self.queued -= len(oldest.texts)
            self.dropped += len(oldest.texts)
        self._ready.set()

    def take(self) -> list[Chunk]:
        """The oldest waiting chunks, whole, up to ``MAX_LIVE_BATCH`` messages in all (at least one chunk
        when any waits)."""
        taken: list[Chunk] = []
        count = 0
        while self._chunks and (not taken or count + len(self._chunks[0].texts) <= MAX_LIVE_BATCH):
            chunk = self._chunks.popleft()
            taken.append(chunk)
            count += len(chunk.texts)
        self.queued -= count
        if not self._chunks:
            self._ready.clear()
        return taken

    def close(self) -> None:
        """The subscriber's socket closed: wake whoever waits in ``next``."""
        self.closed = True
        self._ready.set()

    async def next(self, timeout_s: float) -> list[Chunk]:
        """``take`` once something waits; an empty list when nothing came within ``timeout_s`` or once
        the subscription is closed."""
        if self.closed:
            return []
        if not self._chunks:
            try:
                async with asyncio.timeout(timeout_s):
                    await self._ready.wait()
            except TimeoutError:
                return []
        return self.take()


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
            self._offer(building_id, [live_json(m) for m in messages])

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
        """The texts to every subscriber of the building, serialised and joined once for all of them."""
        subs = self._subs.get(building_id)
        if not subs or not texts:
            return
        for chunk in chunks_of(texts):
            for sub in subs:
                sub.offer(chunk)
        self.published += len(texts)

    def subscribers(self, building_id: str | None = None) -> int:
        if building_id is None:
            return sum(len(s) for s in self._subs.values())
        return len(self._subs.get(building_id, ()))

    def queue_depths(self) -> list[int]:
        return [sub.queued for subs in self._subs.values() for sub in subs]
