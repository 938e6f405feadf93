"""The batch stream on the local NATS JetStream: a building's batches are read in order from any sequence
on, and only that building's."""

from __future__ import annotations

import asyncio
import uuid

from server.cluster.batch_stream import BatchStream, StreamedBatch
from tests.server.cluster.local_nats import connect_or_skip


def test_a_buildings_batches_are_read_in_order_from_any_sequence() -> None:
    async def scenario() -> None:
        connection = await connect_or_skip()
        js = connection.jetstream()
        tag = uuid.uuid4().hex[:10]
        stream = BatchStream(name=f"CROWDSLAM_TEST_{tag}", prefix=f"crowdslam-test-{tag}")
        try:
            await stream.ensure(js, retention_s=600)
            await stream.ensure(js, retention_s=600)  # a second front finds it there
            stored: dict[tuple[str, int], int] = {}
            for k in range(6):
                for building in ("mall:north", "hq"):
                    stored[building, k] = await stream.publish(js, building, f"{building} {k}".encode())
            north = [stored["mall:north", k] for k in range(6)]

            async def first(n: int, after: int) -> list[StreamedBatch]:
                got: list[StreamedBatch] = []
                async for batch in stream.read(js, "mall:north", after):
                    got.append(batch)
                    if len(got) == n:
                        break
                return got

            everything = await asyncio.wait_for(first(6, 0), timeout=10)
            assert [b.body for b in everything] == [f"mall:north {k}".encode() for k in range(6)]
            assert [b.sequence for b in everything] == north
            # a worker that took the building over goes on after the last sequence it finds committed
            rest = await asyncio.wait_for(first(2, north[3]), timeout=10)
            assert [b.body for b in rest] == [b"mall:north 4", b"mall:north 5"]
            # and then gets what comes next, as it comes
            reader = asyncio.create_task(first(1, north[-1]))
            await asyncio.sleep(0.3)
            await stream.publish(js, "mall:north", b"mall:north 6")
            assert [b.body for b in await asyncio.wait_for(reader, timeout=10)] == [b"mall:north 6"]
        finally:
            await js.delete_stream(stream.name)
            await connection.close()

    asyncio.run(scenario())
