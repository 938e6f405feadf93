"""The batches of every building in one JetStream stream, a subject per building. A front publishes each
accepted batch with its building and batch id as JetStream's message id, so a front that retries a publish
(its answer lost) stores it once. A worker that owns a building reads the building's subject in order from the
sequence after the last one it applied, which it keeps in the same SQL transaction as the batches themselves:
whatever JetStream redelivers, nothing is applied twice or out of order, and a worker that takes a building
over goes on from where the last one committed."""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass

from nats.js import JetStreamContext
from nats.js.api import ConsumerConfig, DeliverPolicy, StreamConfig
from nats.js.errors import NotFoundError

from server.cluster.names import building_token

DUPLICATE_WINDOW_S = 120.0
"""How long JetStream remembers a message id: a front's retried publish within it is stored once (a phone's
later retry is a duplicate that the worker's batch log refuses)."""


@dataclass(frozen=True)
class StreamedBatch:
    sequence: int
    """The stream's sequence: the worker stores the last one it applied with the building's state."""
    body: bytes


@dataclass(frozen=True)
class BatchStream:
    name: str = "CROWDSLAM_BATCHES"
    prefix: str = "crowdslam.batches"

    def subject(self, building_id: str) -> str:
        return f"{self.prefix}.{building_token(building_id)}"

    async def ensure(self, js: JetStreamContext, retention_s: float) -> None:
        """Create the stream if it does not exist (each message kept ``retention_s``)."""
        try:
            await js.stream_info(self.name)
        except NotFoundError:
            config = StreamConfig(
                name=self.name,
                subjects=[f"{self.prefix}.*"],
                max_age=retention_s,
                duplicate_window=DUPLICATE_WINDOW_S,
            )
            await js.add_stream(config)

    async def publish(
        self, js: JetStreamContext, building_id: str, batch_id: str, body: bytes
    ) -> tuple[int, bool]:
        """Store one batch; returns its sequence and whether the stream had it already (a retried publish)."""
        headers = {"Nats-Msg-Id": f"{building_id}/{batch_id}"}
        ack = await js.publish(self.subject(building_id), body, stream=self.name, headers=headers)
        return ack.seq, bool(ack.duplicate)

    async def read(
        self, js: JetStreamContext, building_id: str, after_sequence: int
    ) -> AsyncIterator[StreamedBatch]:
        """The building's batches after ``after_sequence``, in the stream's order, then as they come: an
        ordered consumer (JetStream's only consumer that keeps order; it recreates itself after a gap)."""
        config = ConsumerConfig(
            deliver_policy=DeliverPolicy.BY_START_SEQUENCE, opt_start_seq=after_sequence + 1
        )
        subscription = await js.subscribe(
            self.subject(building_id), stream=self.name, ordered_consumer=True, config=config
        )
        try:
            async for message in subscription.messages:
                yield StreamedBatch(message.metadata.sequence.stream, message.data)
        finally:
            await subscription.unsubscribe()
