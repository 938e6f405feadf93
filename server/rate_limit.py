"""Per device key, a token bucket: a phone may post ``burst`` batches at once and ``rate_per_s`` a second
after that. A phone posting once a second never meets it; a client flooding a building is refused with 429
and ``Retry-After`` before its batch is read any further than its key."""

from __future__ import annotations

import math
import time


class RateLimiter:
    def __init__(self, rate_per_s: float, burst: float, max_keys: int = 100_000) -> None:
        self.rate_per_s = rate_per_s
        self.burst = burst
        self.max_keys = max_keys
        self._buckets: dict[int, tuple[float, float]] = {}  # key id -> (tokens, at monotonic time)

    def take(self, key_id: int, now: float | None = None) -> float:
        """Spend one request of this key; 0 when allowed, else the seconds until one is (nothing spent)."""
        if self.rate_per_s <= 0:
            return 0.0
        now = time.monotonic() if now is None else now
        tokens, at = self._buckets.get(key_id, (self.burst, now))
        tokens = min(self.burst, tokens + (now - at) * self.rate_per_s)
        if tokens < 1.0:
            self._buckets[key_id] = (tokens, now)
            return (1.0 - tokens) / self.rate_per_s
        if len(self._buckets) >= self.max_keys and key_id not in self._buckets:
            self._buckets.clear()  # full buckets are the default: forgetting them forgives no one long
        self._buckets[key_id] = (tokens - 1.0, now)
        return 0.0


def retry_after_header(seconds: float) -> str:
    return str(max(1, math.ceil(seconds)))
