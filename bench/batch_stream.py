"""Batch-stream benchmark: what cluster mode's JetStream stream costs per batch on this machine.

    python bench/batch_stream.py [--batches 20000] [--in-flight 64] [--nats URL] [--json OUT]

Publishes real sensor batches (the paper testbed's simulated phones, as JSON, cycled) to a fresh stream of
``server.cluster.batch_stream.BatchStream`` on a local NATS server, first one at a time (each publish awaits
its acknowledgement, as a front answering one phone would), then ``--in-flight`` at a time (a front serving
many phones at once), then reads them all back through the ordered consumer a worker uses. Reports batches a
second and CPU microseconds a batch of this client and of the nats-server process (from /proc, so NATS must
run on this machine), and the stream's bytes a batch. The stream is deleted afterwards.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nats
from report import emit

from server.cluster.batch_stream import BatchStream
from server.simulation.phones import simulated_batches
from slam_core.sim.simulation import Scenario, simulate

SCENARIO = ROOT / "server" / "data" / "paper-testbed.json"
CLOCK_TICKS = 100  # /proc's CPU times are in clock ticks (USER_HZ)


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def _nats_pid() -> int:
    found = subprocess.run(["pgrep", "-o", "nats-server"], capture_output=True, text=True).stdout.split()
    if not found:
        raise SystemExit("no nats-server process on this machine: its CPU cannot be measured")
    return int(found[0])


class Meter:
    """Wall time, and CPU of this process and of nats-server, over a ``with`` block."""

    def __init__(self, nats_pid: int) -> None:
        self.nats_pid = nats_pid

    def __enter__(self) -> Meter:
        self.wall, self.mine, self.server = time.perf_counter(), time.process_time(), _cpu_s(self.nats_pid)
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall = time.perf_counter() - self.wall
        self.mine = time.process_time() - self.mine
        self.server = _cpu_s(self.nats_pid) - self.server

    def row(self, n: int) -> dict[str, float]:
        return {
            "batches_per_s": round(n / self.wall),
            "client_cpu_us_per_batch": round(self.mine / n * 1e6, 1),
            "nats_cpu_us_per_batch": round(self.server / n * 1e6, 1),
        }


async def run(url: str, n: int, in_flight: int, bodies: list[bytes]) -> dict[str, Any]:
    connection = await nats.connect(url)
    js = connection.jetstream()
    tag = uuid.uuid4().hex[:8]
    stream = BatchStream(name=f"CROWDSLAM_BENCH_{tag}", prefix=f"crowdslam-bench-{tag}")
    meter = Meter(_nats_pid())
    result: dict[str, Any] = {"batches": n, "in_flight": in_flight}
    try:
        await stream.ensure(js, retention_s=3600)
        with meter:
            for k in range(n):
                await stream.publish(js, "mall", bodies[k % len(bodies)])
        result["one_at_a_time"] = meter.row(n)
        with meter:
            for start in range(0, n, in_flight):
                await asyncio.gather(*(
                    stream.publish(js, "mall", bodies[k % len(bodies)])
                    for k in range(start, min(n, start + in_flight))
                ))  # fmt: skip
        result["concurrent"] = meter.row(n)
        read = 0
        with meter:
            async for _ in stream.read(js, "mall", 0):
                read += 1
                if read == 2 * n:
                    break
        result["ordered_read"] = meter.row(2 * n)
        info = await js.stream_info(stream.name)
        result["stream_bytes_per_batch"] = round(info.state.bytes / info.state.messages)
        result["body_bytes_mean"] = round(sum(len(b) for b in bodies) / len(bodies))
    finally:
        await js.delete_stream(stream.name)
        await connection.close()
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, default=20_000)
    parser.add_argument("--in-flight", type=int, default=64)
    parser.add_argument("--nats", default="nats://127.0.0.1:4222")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    sim = simulate(Scenario.from_dict(json.loads(SCENARIO.read_text())), 0)
    bodies = [b.model_dump_json(exclude_none=True).encode() for b in simulated_batches(sim, "mall")][:2000]
    emit(asyncio.run(run(args.nats, args.batches, args.in_flight, bodies)), args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
