"""Stream against POST: what the server's front spends on a batch a phone streams over its WebSocket
(``/v1/buildings/{id}/stream``) against one it posts (``POST .../batches`` on a keep-alive connection).

    python bench/stream_vs_post.py [--users 40] [--rounds 6] [--json OUT]

A fresh server (``crowdslam serve``, SQLite, the README's defaults: each building in a process of its own)
tracks the paper testbed's simulated phones. Their batches, in time order, are cut into ``2 * --rounds``
stretches sent alternately by POST and by the stream (each phone keeps one connection of each kind, and
sends its batches of a stretch one after another's answer, all phones at once), so that both transports
meet the same building at the same load and a drift of the machine's speed falls on both. For each
transport: the front's CPU microseconds a batch (its process only: the building's is the same work either
way), the building processes' likewise, the client's, and the median answer time. Every answer must be a
receipt (``applied``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import httpx
import numpy as np
from load import _cpu_seconds
from report import emit
from websockets.asyncio.client import connect

from schemas.sensors import SensorBatch
from server.cli.background_server import free_port, migrate_with_operator_key, serve_process
from server.simulation.crowd_client import device_keys, prepare_building
from server.simulation.phones import simulated_batches
from slam_core.sim.simulation import Scenario, simulate

SCENARIO = ROOT / "server" / "data" / "paper-testbed.json"


async def _stretch(
    transport: str,
    port: int,
    by_phone: dict[str, list[bytes]],
    keys: dict[str, str],
    posts: dict[str, httpx.AsyncClient],
    streams: dict[str, Any],
) -> list[float]:
    """Every phone sends its batches of the stretch, one after another's answer, all phones at once: the
    answer times (ms)."""
    times: list[float] = []

    async def phone(device: str, bodies: list[bytes]) -> None:
        for body in bodies:
            started = time.perf_counter()
            if transport == "post":
                response = await posts[device].post(
                    f"http://127.0.0.1:{port}/v1/buildings/hq/batches",
                    content=body,
                    headers={"Authorization": f"Bearer {keys[device]}", "Content-Type": "application/json"},
                )
                answer = response.text
                if response.status_code != 200:
                    raise RuntimeError(f"POST answered {response.status_code}: {answer}")
            else:
                await streams[device].send(body.decode())
                answer = str(await streams[device].recv())
            if json.loads(answer).get("status") != "applied":
                raise RuntimeError(f"{transport}: not applied: {answer}")
            times.append((time.perf_counter() - started) * 1e3)

    await asyncio.gather(*(phone(d, b) for d, b in by_phone.items() if b))
    return times


async def _measure(
    port: int, pid: int, batches: list[SensorBatch], keys: dict[str, str], rounds: int
) -> dict:
    cuts = np.array_split(np.arange(len(batches)), 2 * rounds)
    posts = {d: httpx.AsyncClient(timeout=60.0) for d in keys}
    streams = {
        d: await connect(f"ws://127.0.0.1:{port}/v1/buildings/hq/stream?token={k}", max_size=None)
        for d, k in keys.items()
    }
    figures: dict[str, dict[str, float]] = {
        t: {"batches": 0, "front_s": 0.0, "buildings_s": 0.0, "client_s": 0.0} for t in ("post", "stream")
    }
    latencies: dict[str, list[float]] = {"post": [], "stream": []}
    try:
        for k, cut in enumerate(cuts):
            transport = ("post", "stream")[k % 2]
            by_phone: dict[str, list[bytes]] = {d: [] for d in keys}
            for i in cut.tolist():
                by_phone[batches[i].device_id].append(batches[i].model_dump_json(exclude_none=True).encode())
            front, server, client = _cpu_seconds(pid), _cpu_seconds(pid, children=True), time.process_time()
            latencies[transport] += await _stretch(transport, port, by_phone, keys, posts, streams)
            f = figures[transport]
            f["batches"] += cut.size
            front = _cpu_seconds(pid) - front
            f["front_s"] += front
            f["buildings_s"] += _cpu_seconds(pid, children=True) - server - front
            f["client_s"] += time.process_time() - client
    finally:
        for client in posts.values():
            await client.aclose()
        for stream in streams.values():
            await stream.close()
    out: dict[str, Any] = {}
    for transport, f in figures.items():
        n = max(f["batches"], 1)
        out[transport] = {
            "batches": int(f["batches"]),
            "front_us_per_batch": round(1e6 * f["front_s"] / n, 1),
            "building_us_per_batch": round(1e6 * f["buildings_s"] / n, 1),
            "client_us_per_batch": round(1e6 * f["client_s"] / n, 1),
            "answer_ms_p50": round(float(np.median(latencies[transport])), 2),
        }
    out["front_stream_vs_post"] = round(
        out["stream"]["front_us_per_batch"] / max(out["post"]["front_us_per_batch"], 1e-9), 3
    )
    return out


def run(users: int, rounds: int) -> dict[str, Any]:
    raw = json.loads(SCENARIO.read_text())
    raw["users"]["count"] = users
    sim = simulate(Scenario.from_dict(raw), 0)
    batches = list(simulated_batches(sim, "hq"))
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "CROWDSLAM_DATA_DIR": tmp, "CROWDSLAM_DEVICE_RATE_PER_S": "1000"}
        operator = migrate_with_operator_key(env)
        port = free_port()
        server = serve_process(env, port, Path(tmp) / "server.log", log_level="warning")
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as client:
                prepare_building(client, "hq", operator, sim)
                keys = device_keys(client, "hq", operator, len(sim.users))
            result = asyncio.run(_measure(port, server.pid, batches, keys, rounds))
        finally:
            server.terminate()
            server.wait(timeout=120)
    return {"users": users, "rounds": rounds, **result}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--users", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    emit(run(args.users, args.rounds), args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
