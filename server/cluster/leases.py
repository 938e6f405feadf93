"""Which worker owns which building: a lease per building in a JetStream key-value bucket whose entries
expire ``ttl_s`` after their last write. A worker takes a free building with ``create`` (it fails when the
key holds a live lease), keeps it by rewriting it with compare-and-swap on its revision (``update``: a lease
someone else took since fails), and a worker that dies stops rewriting, so its leases expire within ``ttl_s``
and another worker's ``create`` succeeds (``server.cluster.ttl_buckets``)."""

from __future__ import annotations

from dataclasses import dataclass

from nats.js import JetStreamContext
from nats.js.errors import (
    BadRequestError,
    KeyDeletedError,
    KeyNotFoundError,
    KeyWrongLastSequenceError,
)
from nats.js.kv import KeyValue

from server.cluster.names import building_token
from server.cluster.ttl_buckets import ttl_bucket

BUCKET = "crowdslam-leases"
WRONG_LAST_SEQUENCE = 10071
"""JetStream's error code when a write's expected revision is not the key's (a delete reports it raw)."""


class LeaseLostError(RuntimeError):
    """The lease was taken by another worker or expired: the building is no longer this worker's."""

    def __init__(self, building_id: str, owner: str) -> None:
        super().__init__(f"{owner} no longer holds the lease on building {building_id!r}")
        self.building_id = building_id


@dataclass(frozen=True)
class Lease:
    building_id: str
    owner: str
    revision: int
    """The bucket's sequence of the lease's latest write: the compare-and-swap token of the next refresh."""


class Leases:
    def __init__(self, kv: KeyValue, owner: str) -> None:
        self.kv = kv
        self.owner = owner

    @classmethod
    async def open(cls, js: JetStreamContext, owner: str, ttl_s: float, bucket: str = BUCKET) -> Leases:
        """The lease bucket, created with ``ttl_s`` if it does not exist yet."""
        kv = await ttl_bucket(js, bucket, ttl_s)
        return cls(kv, owner)

    async def acquire(self, building_id: str) -> Lease | None:
        """The building's lease, if no live lease holds it; None otherwise."""
        try:
            revision = await self.kv.create(building_token(building_id), self.owner.encode())
        except (KeyWrongLastSequenceError, KeyNotFoundError):
            # KeyNotFoundError: the create met a live lease, which expired before nats-py's check of it read
            # the key back; it was held a moment ago, and the next attempt takes it
            return None
        return Lease(building_id, self.owner, revision)

    async def refresh(self, lease: Lease) -> Lease:
        """Rewrite the lease, so that it lives another TTL; ``LeaseLostError`` if it expired or was taken."""
        try:
            revision = await self.kv.update(
                building_token(lease.building_id), self.owner.encode(), last=lease.revision
            )
        except (KeyWrongLastSequenceError, KeyNotFoundError, KeyDeletedError) as error:
            raise LeaseLostError(lease.building_id, self.owner) from error
        return Lease(lease.building_id, self.owner, revision)

    async def release(self, lease: Lease) -> None:
        """Give the building up now (a clean handoff), unless the lease is no longer this worker's."""
        try:
            await self.kv.delete(building_token(lease.building_id), last=lease.revision)
        except (KeyWrongLastSequenceError, KeyNotFoundError, KeyDeletedError):
            return
        except BadRequestError as error:
            if error.err_code != WRONG_LAST_SEQUENCE:
                raise

    async def owner_of(self, building_id: str) -> str | None:
        """The worker holding the building's live lease, or None."""
        try:
            entry = await self.kv.get(building_token(building_id))
        except (KeyNotFoundError, KeyDeletedError):
            return None
        return None if entry.value is None else entry.value.decode()
