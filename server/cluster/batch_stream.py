"""The batches of every building in one JetStream stream, a subject per building. A front publishes each
accepted batch; the worker that owns the building reads the building's subject in order from the sequence
after the last one it applied, which it keeps in the same SQL transaction as the batches themselves (the
commit is the acknowledgement). Whatever JetStream delivers again, nothing is applied twice or out of order,
and a worker that takes a building over goes on from where the last one committed. A batch a phone sends
again is stored again: the worker's batch log recognises it (``duplicate``), so a retry after a lost answer
gets its receipt from the worker (JetStream's message-id dedupe would drop the retry, and its answer with
it)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass

from nats.js import JetStreamContext
from nats.js.api import ConsumerConfig, DeliverPolicy, StreamConfig
from nats.js.errors import NotFoundError

from server.cluster.names import building_token


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
            )
            await js.add_stream(config)

    async def publish(self, js: JetStreamContext, building_id: str, body: bytes) -> int:
        """Store one batch; its sequence in the stream."""
        ack = await js.publish(self.subject(building_id), body, stream=self.name)
        return int(ack.seq)

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
