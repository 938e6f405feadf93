"""JetStream key-value buckets whose entries expire a fixed time after their last write: the workers' leases
(``server.cluster.leases``) and heartbeats (``server.cluster.members``). The bucket's own expiry
(``max_age``) is the TTL: per-key TTL markers need nats-server 2.11, and every entry has the same TTL."""

from __future__ import annotations

from nats.js import JetStreamContext
from nats.js.api import KeyValueConfig
from nats.js.errors import BucketNotFoundError
from nats.js.kv import KeyValue


class BucketTTLMismatchError(RuntimeError):
    """The bucket exists with another TTL: workers that disagree on it would take buildings too early, or
    count a live worker as gone."""


async def ttl_bucket(js: JetStreamContext, bucket: str, ttl_s: float) -> KeyValue:
    """The bucket, created with ``ttl_s`` (one revision a key) if it does not exist yet."""
    try:
        kv = await js.key_value(bucket)
    except BucketNotFoundError:
        kv = await js.create_key_value(KeyValueConfig(bucket=bucket, ttl=ttl_s, history=1))
    status = await kv.status()
    if status.ttl is not None and abs(status.ttl - ttl_s) > 1e-3:
        raise BucketTTLMismatchError(
            f"bucket {bucket!r} has a TTL of {status.ttl:g} s, this worker's is {ttl_s:g} s: every worker "
            "must use the same CROWDSLAM_LEASE_TTL_S"
        )
    return kv
