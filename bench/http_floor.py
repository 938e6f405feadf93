"""The HTTP floor: what uvicorn itself costs a POSTed batch on this machine, under which no front can go.

    python bench/http_floor.py [--phones 1000] [--duration 20] [--json OUT]

The load benchmark's phones (``bench/load.py``: the same bodies, one a second each, spread evenly over the
second, over the same pool of keep-alive connections) post to uvicorn, started as ``crowdslam serve``
starts it (uvloop and httptools where installed, the default log level), serving an ASGI app that reads
each body and answers a fixed receipt: no key, no validation, no building. The server's CPU microseconds a
request (from /proc, over the measured seconds) is the floor of the server's own
``front_us_per_batch``, which adds the key's check, validation and conversion, and the hand-off to the
building and back. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np
from load import Crowd, Posts, _body, _cpu_seconds
from report import emit

from server.cli.background_server import free_port

RECEIPT = b'{"status":"applied","batch_id":"load-00000-5","estimate":null}'


async def app(scope: dict[str, Any], receive: Any, send: Any) -> None:
    """Reads the request's body to its end and answers the receipt (lifespan accepted, nothing else)."""
    if scope["type"] == "lifespan":
        while True:
            message = await receive()
            if message["type"] == "lifespan.startup":
                await send({"type": "lifespan.startup.complete"})
            elif message["type"] == "lifespan.shutdown":
                await send({"type": "lifespan.shutdown.complete"})
                return
    more = True
    while more:
        message = await receive()
        more = message.get("more_body", False)
    await send(
        {
            "type": "http.response.start",
            "status": 200,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(RECEIPT)).encode()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": RECEIPT})


async def _drive(port: int, phones: int, duration_s: float, server_pid: int) -> dict[str, Any]:
    crowd = Crowd.create(phones, seed=0)
    near = crowd.neighbours()
    now_ms = int(time.time() * 1000)
    bodies = [_body(crowd, phone, 5, now_ms, near[phone], "b0") for phone in range(phones)]
    statuses: list[int] = []
    posts = Posts([port], min(phones, 256), lambda status, due, measured: statuses.append(status))
    await posts.open()
    phase = np.linspace(0.0, 1.0, phones, endpoint=False)
    warmup_s = 3
    start = time.perf_counter()
    measured_from = None
    for second in range(math.ceil(duration_s) + warmup_s):
        if second == warmup_s:
            measured_from = (
                _cpu_seconds(server_pid),
                _cpu_seconds(os.getpid()),
                time.perf_counter(),
                len(statuses),
            )
        at = 0
        while at < phones:
            delay = start + second + phase[at] - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            now = time.perf_counter()
            while at < phones and start + second + phase[at] <= now:
                posts.post("/v1/buildings/b0/batches", "key", bodies[at], now, True)
                at += 1
    while len(statuses) < phones * (math.ceil(duration_s) + warmup_s):
        await asyncio.sleep(0.01)
    assert measured_from is not None
    server_s = _cpu_seconds(server_pid) - measured_from[0]
    generator_s = _cpu_seconds(os.getpid()) - measured_from[1]
    answered = len(statuses) - measured_from[3]
    posts.close()
    return {
        "phones": phones,
        "requests": answered,
        "errors": sum(status != 200 for status in statuses),
        "server_us_per_request": round(server_s / answered * 1e6, 1),
        "server_cores": round(server_s / (time.perf_counter() - measured_from[2]), 3),
        "generator_us_per_request": round(generator_s / answered * 1e6, 1),
        "body_bytes_mean": round(float(np.mean([len(b) for b in bodies])), 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--phones", type=int, default=1000)
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    port = free_port()
    server = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import uvicorn; uvicorn.run('http_floor:app', port={port}, log_level='warning')",
        ],
        cwd=Path(__file__).parent,
    )
    try:
        for _ in range(200):
            try:
                asyncio.run(asyncio.wait_for(asyncio.open_connection("127.0.0.1", port), 1.0))
                break
            except OSError:
                time.sleep(0.05)
        result = asyncio.run(_drive(port, args.phones, args.duration, server.pid))
    finally:
        server.terminate()
        server.wait(timeout=10)
    emit(result, args.json)
    return 0 if result["errors"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
