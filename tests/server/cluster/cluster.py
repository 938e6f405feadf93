"""A real cluster for the tests: a private ``nats-server -js`` on a free loopback port (so that a test may
stop and restart it), a new database on the local PostgreSQL, fronts and workers as ``crowdslam serve``
processes; and phones that post the simulated testbed's batches through the fronts as real phones do (one
batch at a time, the same batch again after a 503 or a lost connection, to another front when one is
gone)."""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
from sqlalchemy import text

from schemas.api import BatchReceipt
from schemas.sensors import SensorBatch
from server.cli.background_server import free_port, migrate_with_operator_key, serve_process
from server.cli.local_cluster import nats_server, postgres_database, worker_process
from server.cluster.leases import BUCKET
from server.cluster.names import building_token
from server.simulation.crowd_client import device_keys, prepare_building
from server.simulation.phones import simulated_batches
from server.store.db import make_engine
from slam_core.sim.simulation import Scenario, Simulation, simulate
from tests.conftest import POSTGRES_ADMIN_URL, TESTBED

LEASE_TTL_S = 3.0
RECEIPT_TIMEOUT_S = 4.0


def _required(what: str) -> None:
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"{what} is required under CI=true")
    pytest.skip(f"{what} is not available here")


def small_crowd(users: int = 3, walk_length_m: float = 40.0, seed: int = 4) -> Simulation:
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = users
    raw["users"]["walk_length_m"] = walk_length_m
    return simulate(Scenario.from_dict(raw), seed)


@dataclass
class Cluster:
    root: Path
    env: dict[str, str]
    nats_port: int
    nats: subprocess.Popen[bytes]
    operator: str
    fronts: list[tuple[int, subprocess.Popen[bytes]]] = field(default_factory=list)
    workers: list[subprocess.Popen[bytes]] = field(default_factory=list)

    # ------------------------------------------------------------------ processes
    def start_front(self) -> int:
        port = free_port()
        process = serve_process(
            {**self.env, "CROWDSLAM_ROLE": "front"}, port, self.root / f"front-{port}.log"
        )
        self.fronts.append((port, process))
        return port

    def start_worker(self) -> subprocess.Popen[bytes]:
        process = worker_process(self.env, self.root / f"worker-{len(self.workers)}.log")
        self.workers.append(process)
        return process

    def front_urls(self) -> list[str]:
        return [f"http://127.0.0.1:{port}" for port, p in self.fronts if p.poll() is None]

    def kill(self, process: subprocess.Popen[bytes]) -> None:
        process.send_signal(signal.SIGKILL)
        process.wait()

    def restart_nats(self, down_s: float = 1.0) -> None:
        """Stop NATS (its streams and buckets stay on disk), wait, start it again on the same port."""
        self.nats.terminate()
        self.nats.wait(timeout=30)
        time.sleep(down_s)
        self.nats = nats_server(self.nats_port, self.root / "nats", self.root / "nats.log")

    def stop(self) -> None:
        """SIGTERM to every process (a worker hands its buildings off); a process that does not stop within
        a minute fails the test, after a worker has logged where its tasks wait."""
        for _, process in self.fronts:
            process.terminate()
        for process in self.workers:
            process.terminate()
        hung = []
        for process in [p for _, p in self.fronts] + self.workers:
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                hung.append(process.pid)
                process.send_signal(signal.SIGUSR1)
                time.sleep(1.0)
                process.kill()
                process.wait()
        self.nats.terminate()
        self.nats.wait(timeout=30)
        assert not hung, f"processes {hung} did not stop on SIGTERM within 60 s\n{self.logs()}"

    def logs(self) -> str:
        return "\n".join(f"==> {p.name}\n{p.read_text()[-4000:]}" for p in sorted(self.root.glob("*.log")))

    # ------------------------------------------------------------------ what the cluster holds
    def owners(self) -> dict[str, str | None]:
        """Each building's lease holder (the worker's id: host-pid-nonce), from the lease bucket."""
        import nats

        async def read() -> dict[str, str | None]:
            connection = await nats.connect(f"nats://127.0.0.1:{self.nats_port}", max_reconnect_attempts=0)
            try:
                kv = await connection.jetstream().key_value(BUCKET)
                found: dict[str, str | None] = {}
                for building in self.buildings():
                    try:
                        entry = await kv.get(building_token(building))
                        found[building] = None if entry.value is None else entry.value.decode()
                    except Exception:
                        found[building] = None
                return found
            finally:
                await connection.close()

        return asyncio.run(read())

    def publish_foreign(self, building: str, batch: SensorBatch) -> None:
        """Put a batch in the stream as a front of an earlier database would have, for an earlier building of
        the same id."""
        import nats

        from server.buildings.submissions import Submission, batch_fields
        from server.cluster import messages
        from server.cluster.batch_stream import BatchStream

        raw = batch.model_dump_json(exclude_none=True).encode()
        body = messages.encode_stream_batch(
            "crowdslam.receipts.gone.0",
            "1999-01-01T00:00:00+00:00",
            batch_fields(Submission.of(batch, raw, time.time_ns())),
        )

        async def publish() -> None:
            connection = await nats.connect(f"nats://127.0.0.1:{self.nats_port}", max_reconnect_attempts=0)
            try:
                await BatchStream().publish(connection.jetstream(), building, body)
            finally:
                await connection.close()

        asyncio.run(publish())

    def owner_pids(self) -> dict[str, int | None]:
        return {b: None if o is None else int(o.split("-")[-2]) for b, o in self.owners().items()}

    def wait_until_shared(self, workers: int, timeout_s: float = 60.0) -> dict[str, int | None]:
        """Wait until every building is held and each of ``workers`` live workers holds its share."""
        deadline = time.monotonic() + timeout_s
        while True:
            owners = self.owner_pids()
            held = [pid for pid in owners.values() if pid is not None]
            counts = {pid: held.count(pid) for pid in set(held)}
            share = -(-len(owners) // workers)
            if len(held) == len(owners) and len(counts) == workers and max(counts.values()) <= share:
                return owners
            if time.monotonic() > deadline:
                raise AssertionError(f"buildings not shared by {workers} workers: {owners}\n{self.logs()}")
            time.sleep(0.2)

    def buildings(self) -> list[str]:
        engine = make_engine(self.env["CROWDSLAM_DATABASE_URL"])
        try:
            with engine.connect() as connection:
                return sorted(connection.execute(text("SELECT id FROM buildings")).scalars())
        finally:
            engine.dispose()

    def stored_batches(self) -> set[tuple[str, str, str]]:
        """(building, device, batch id) of every batch in the store's batch log."""
        engine = make_engine(self.env["CROWDSLAM_DATABASE_URL"])
        try:
            with engine.connect() as connection:
                rows = connection.execute(text("SELECT building_id, device_id, batch_id FROM batches")).all()
        finally:
            engine.dispose()
        return {(str(b), str(d), str(i)) for b, d, i in rows}


@contextmanager
def local_cluster(root: Path, fronts: int = 2, workers: int = 2) -> Iterator[Cluster]:
    if shutil.which("nats-server") is None:
        _required("nats-server")
    try:
        database = postgres_database(POSTGRES_ADMIN_URL, prefix="crowdslam_cluster")
        url = database.__enter__()
    except Exception as error:
        _required(f"PostgreSQL ({str(error).splitlines()[0]})")
        raise
    nats_port = free_port()
    nats = nats_server(nats_port, root / "nats", root / "nats.log")
    env = {
        **os.environ,
        "CROWDSLAM_DATA_DIR": str(root),
        "CROWDSLAM_DATABASE_URL": url,
        "CROWDSLAM_NATS_URL": f"nats://127.0.0.1:{nats_port}",
        "CROWDSLAM_LEASE_TTL_S": str(LEASE_TTL_S),
        "CROWDSLAM_RECEIPT_TIMEOUT_S": str(RECEIPT_TIMEOUT_S),
        "CROWDSLAM_SNAPSHOT_PERIOD_S": "2",
        "CROWDSLAM_DEVICE_RATE_PER_S": "0",
    }
    cluster: Cluster | None = None
    try:
        cluster = Cluster(root, env, nats_port, nats, migrate_with_operator_key(env))
        for _ in range(workers):
            cluster.start_worker()
        for _ in range(fronts):
            cluster.start_front()
        yield cluster
    finally:
        if cluster is not None:
            cluster.stop()
        else:
            nats.terminate()
            nats.wait()
        database.__exit__(None, None, None)


# ---------------------------------------------------------------------------------------------- phones
@dataclass
class Answer:
    building: str
    batch_id: str
    device_id: str
    status: int
    receipt: BatchReceipt | None
    at: float
    retry_of_acknowledged: bool = False


@dataclass
class Crowd:
    """Phones of several buildings, each posting its batches in order, one at a time."""

    cluster: Cluster
    sim: Simulation
    buildings: list[str]
    keys: dict[str, dict[str, str]] = field(default_factory=dict)
    batches: dict[str, list[SensorBatch]] = field(default_factory=dict)
    answers: list[Answer] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def prepare(self) -> None:
        with httpx.Client(base_url=self.cluster.front_urls()[0], timeout=30.0) as client:
            for building in self.buildings:
                prepare_building(client, building, self.cluster.operator, self.sim)
                self.keys[building] = device_keys(
                    client, building, self.cluster.operator, len(self.sim.users)
                )
                self.batches[building] = list(simulated_batches(self.sim, building))

    def post(self, every_s: float = 0.0, on_progress: Callable[[float], None] | None = None) -> None:
        """Every phone posts all its batches (``every_s`` apart), retrying each until a front answers 200;
        ``on_progress`` hears the fraction of batches acknowledged as it grows."""
        phones = [
            (building, device, [b for b in self.batches[building] if b.device_id == device])
            for building in self.buildings
            for device in sorted(self.keys[building])
        ]
        total = sum(len(b) for _, _, b in phones)
        done = itertools.count(1)

        def phone(index: int, building: str, device: str, batches: list[SensorBatch]) -> None:
            clients = [httpx.Client(base_url=u, timeout=30.0) for u in self.cluster.front_urls()]
            turn = index
            try:
                for batch in batches:
                    body = batch.model_dump_json(exclude_none=True)
                    deadline = time.monotonic() + 120.0
                    while True:
                        client = clients[turn % len(clients)]
                        try:
                            response = client.post(
                                f"/v1/buildings/{building}/batches",
                                content=body,
                                headers={"Authorization": f"Bearer {self.keys[building][device]}"},
                            )
                        except httpx.TransportError:
                            turn += 1  # that front is gone: the phone tries another
                            time.sleep(0.2)
                            continue
                        receipt = (
                            BatchReceipt.model_validate_json(response.content)
                            if response.status_code == 200
                            else None
                        )
                        with self._lock:
                            self.answers.append(
                                Answer(
                                    building,
                                    batch.batch_id,
                                    device,
                                    response.status_code,
                                    receipt,
                                    time.time(),
                                )
                            )
                        if response.status_code == 200:
                            break
                        assert response.status_code == 503, response.text
                        assert "retry-after" in response.headers
                        assert time.monotonic() < deadline, f"{building}/{batch.batch_id} never acknowledged"
                        time.sleep(min(float(response.headers["retry-after"]), 0.5))
                    if on_progress is not None:
                        on_progress(next(done) / total)
                    time.sleep(every_s)
            finally:
                for client in clients:
                    client.close()

        threads = [threading.Thread(target=phone, args=(i, *p)) for i, p in enumerate(phones)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()

    def acknowledged(self) -> list[Answer]:
        return [a for a in self.answers if a.status == 200]

    def post_again(self, building: str, batch: SensorBatch) -> BatchReceipt:
        """A phone that sends an acknowledged batch again (its answer lost), through the first live front."""
        with httpx.Client(base_url=self.cluster.front_urls()[0], timeout=30.0) as client:
            response = client.post(
                f"/v1/buildings/{building}/batches",
                content=batch.model_dump_json(exclude_none=True),
                headers={"Authorization": f"Bearer {self.keys[building][batch.device_id]}"},
            )
        assert response.status_code == 200, response.text
        return BatchReceipt.model_validate_json(response.content)
