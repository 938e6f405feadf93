"""The workers of a cluster: each one's entry in a JetStream key-value bucket that forgets it ``ttl_s``
after its last heartbeat. Workers share the buildings out by their number (``server.cluster.worker``)."""

from __future__ import annotations

from nats.js import JetStreamContext
from nats.js.errors import NoKeysError
from nats.js.kv import KeyValue

from server.cluster.ttl_buckets import ttl_bucket

BUCKET = "crowdslam-workers"


class Members:
    def __init__(self, kv: KeyValue, worker_id: str) -> None:
        self.kv = kv
        self.worker_id = worker_id

    @classmethod
    async def open(cls, js: JetStreamContext, worker_id: str, ttl_s: float, bucket: str = BUCKET) -> Members:
        return cls(await ttl_bucket(js, bucket, ttl_s), worker_id)

    async def heartbeat(self) -> None:
        await self.kv.put(self.worker_id, b"")

    async def leave(self) -> None:
        await self.kv.purge(self.worker_id)

    async def live(self) -> set[str]:
        """The workers heard from within the TTL (this one included once it has beaten)."""
        try:
            return set(await self.kv.keys())
        except NoKeysError:
            return set()
