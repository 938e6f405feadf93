"""The local NATS server (127.0.0.1:4222, JetStream on) that the cluster tests talk to."""

from __future__ import annotations

import os

import nats
import pytest
from nats.aio.client import Client

NATS_URL = os.environ.get("CROWDSLAM_TEST_NATS_URL", "nats://127.0.0.1:4222")


async def connect_or_skip() -> Client:
    """A connection to the local NATS; skipped when it is unreachable, failed under CI=true."""
    try:
        return await nats.connect(NATS_URL, connect_timeout=2, max_reconnect_attempts=0)
    except Exception as error:  # any failure to connect means "unreachable" here
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"NATS is required under CI=true but {NATS_URL} is unreachable: {error}")
        pytest.skip(f"NATS unreachable at {NATS_URL}: {error}")
