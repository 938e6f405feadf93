"""The garbage collector tuned for a process whose only job is serving."""

from __future__ import annotations

import gc


def tune_gc_for_serving() -> None:
    """For a process that is the server: everything built so far (compiled kernels, SQLAlchemy and pydantic
    machinery) lives as long as the server, so it is kept out of the cyclic collector, whose full passes
    over it paused the event loop for up to 0.2 s under load; and young collections run every 10,000
    allocations instead of 700, full ones ten times more rarely (the batch path makes few cycles). At 400
    load-bench phones p99 went from 250 ms to 45-100 ms."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(10_000, 10, 100)
