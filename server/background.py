"""Run the app under uvicorn in a background thread (the demo, end-to-end tests, benchmarks)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import uvicorn
from fastapi import FastAPI


class ServerDidNotStartError(RuntimeError):
    pass


@contextmanager
def running_server(app: FastAPI, host: str, port: int, start_timeout_s: float = 120.0) -> Iterator[str]:
    """Start serving ``app``; yields its base URL once it accepts connections, stops it on exit."""
    server = uvicorn.Server(
        uvicorn.Config(app, host=host, port=port, log_level="warning", ws="websockets-sansio")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + start_timeout_s
    while not server.started:
        if not thread.is_alive():
            raise ServerDidNotStartError(f"the server did not start on {host}:{port} (is the port free?)")
        if time.monotonic() > deadline:
            server.should_exit = True
            raise ServerDidNotStartError(f"the server did not start within {start_timeout_s:.0f} s")
        time.sleep(0.05)
    try:
        yield f"http://{host}:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=10)
