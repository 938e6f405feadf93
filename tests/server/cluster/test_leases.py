"""Building leases on the local NATS JetStream: one owner at a time, kept by refreshing, lost within the TTL
when not refreshed, handed over at once when released."""

from __future__ import annotations

import asyncio
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

import pytest
from nats.js import JetStreamContext
from nats.js.errors import KeyNotFoundError

from server.cluster.leases import LeaseLostError, Leases
from server.cluster.members import Members
from server.cluster.names import building_token
from server.cluster.ttl_buckets import BucketTTLMismatchError
from tests.server.cluster.local_nats import connect_or_skip

TTL_S = 2.0


@asynccontextmanager
async def jetstream() -> AsyncIterator[tuple[JetStreamContext, str]]:
    """The local NATS's JetStream and a bucket name of this test's own (deleted afterwards)."""
    connection = await connect_or_skip()
    js = connection.jetstream()
    bucket = f"crowdslam-test-{uuid.uuid4().hex[:12]}"
    try:
        yield js, bucket
    finally:
        try:
            await js.delete_key_value(bucket)
        finally:
            await connection.close()


async def eventually(check: Callable[[], Awaitable[bool]], within_s: float) -> float:
    started = time.monotonic()
    while time.monotonic() - started < within_s:
        if await check():
            return time.monotonic() - started
        await asyncio.sleep(0.1)
    raise AssertionError(f"not within {within_s} s")


def test_one_owner_at_a_time_kept_by_refreshing_and_lost_when_not() -> None:
    async def scenario() -> None:
        async with jetstream() as (js, bucket):
            a = await Leases.open(js, "worker-a", TTL_S, bucket)
            b = await Leases.open(js, "worker-b", TTL_S, bucket)
            lease = await a.acquire("mall:north")
            assert lease is not None
            assert await b.acquire("mall:north") is None
            assert await a.owner_of("mall:north") == "worker-a"
            assert await b.acquire("mall:south") is not None  # other buildings are free
            # refreshed every TTL/3, the lease outlives its TTL
            for _ in range(8):
                await asyncio.sleep(TTL_S / 3)
                lease = await a.refresh(lease)
                assert await b.acquire("mall:north") is None
            # not refreshed, it expires within the TTL (and the expiry's own granularity), then b takes it
            waited = await eventually(lambda: _acquired(b, "mall:north"), within_s=TTL_S + 3)
            assert waited < TTL_S + 3
            assert await b.owner_of("mall:north") == "worker-b"
            with pytest.raises(LeaseLostError):
                await a.refresh(lease)  # a's stale revision: it must stop applying the building's batches

    asyncio.run(scenario())


async def _acquired(leases: Leases, building_id: str) -> bool:
    return await leases.acquire(building_id) is not None


def test_a_released_lease_is_taken_at_once_and_a_stale_release_changes_nothing() -> None:
    async def scenario() -> None:
        async with jetstream() as (js, bucket):
            a = await Leases.open(js, "worker-a", TTL_S, bucket)
            b = await Leases.open(js, "worker-b", TTL_S, bucket)
            lease = await a.acquire("hq")
            assert lease is not None
            await a.release(lease)
            taken = await b.acquire("hq")
            assert taken is not None
            await a.release(lease)  # a's old lease: b's stays
            assert await a.owner_of("hq") == "worker-b"
            assert await a.acquire("hq") is None

    asyncio.run(scenario())


def test_workers_must_agree_on_the_ttl() -> None:
    async def scenario() -> None:
        async with jetstream() as (js, bucket):
            await Leases.open(js, "worker-a", TTL_S, bucket)
            with pytest.raises(BucketTTLMismatchError, match="same CROWDSLAM_LEASE_TTL_S"):
                await Leases.open(js, "worker-b", 2 * TTL_S, bucket)
            # the heartbeats' bucket too: a worker with a longer TTL would count a gone one as live
            members = f"{bucket}-members"
            try:
                await Members.open(js, "worker-a", TTL_S, members)
                with pytest.raises(BucketTTLMismatchError, match="same CROWDSLAM_LEASE_TTL_S"):
                    await Members.open(js, "worker-b", 2 * TTL_S, members)
            finally:
                await js.delete_key_value(members)

    asyncio.run(scenario())


def test_building_tokens_are_valid_keys_and_distinct_for_every_identifier() -> None:
    ids = ["hq", "mall:north", "a.b", "a..b", "A-1_2", "x" * 64]
    keys = [building_token(i) for i in ids]
    assert len(set(keys)) == len(ids)
    assert all(k.isalnum() for k in keys)


def test_a_lease_that_expires_while_it_is_being_taken_is_not_taken_this_time() -> None:
    """nats-py's create meets the live lease, then finds the key gone when it reads it back (the TTL ran out
    in between): that is a lease held a moment ago, not an error; the next attempt takes it."""

    class ExpiringBetween:
        async def create(self, key: str, value: bytes) -> int:
            raise KeyNotFoundError

    leases = Leases(ExpiringBetween(), "worker-b")  # type: ignore[arg-type]
    assert asyncio.run(leases.acquire("mall:north")) is None
