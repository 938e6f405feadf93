"""Run the crash-anywhere scenario against a real server, killed with SIGKILL at seeded points, and compare it
with the same scenario run without a crash.

A kill falls while a request of the scenario is in flight (``KillPoint.delay_s`` after it was sent: before the
server has read it, while the building applies it, or after it answered). Its target is the building's
process (the server starts it again at the next request), the whole server (its process group: restarted
on the same data) or, in a cluster, the worker holding the building (another takes it over). The request is
then sent again until it is answered, as a phone or an operator's script would, and the batches already
acknowledged are sent again: each must answer ``duplicate``.

What must be equal, bit for bit, to the run without a crash: every receipt of a batch applied in both runs,
the users' latest estimates and floors, their position histories, the anchor map, the zones and their
visits, the keys, the signal map
the building loaded, the batches in the recordings; and no building may be failing.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import httpx

from server.cli.background_server import (
    CLI,
    free_port,
    migrate_with_operator_key,
    spawned_processes,
    wait_until_ready,
)
from server.recordings.recorder import read_batches
from tests.server.crash.scenario import BUILDING, CrashScenario, Step

Target = Literal["building", "server", "worker"]
RETRY_S = 120.0
"""How long a request is sent again (503, a lost connection) before the run fails."""
RECENT = 20
"""After a crash, the batches acknowledged last that are sent again (all of them at the end)."""


@dataclass(frozen=True)
class KillPoint:
    step: int
    target: Target
    delay_s: float


def kill_points(scenario: CrashScenario, n: int, seed: int, targets: tuple[Target, ...]) -> list[KillPoint]:
    """``n`` kills at seeded steps (at most one a step), each of a seeded target, up to 30 ms into it."""
    rng = random.Random(seed)
    steps = sorted(rng.sample(scenario.killable, n))
    return [KillPoint(s, rng.choice(targets), rng.uniform(0.0, 0.03)) for s in steps]


class Server(Protocol):
    """What the run drives: a server it can reach, kill and start again."""

    url: str

    def kill(self, target: Target) -> None: ...
    def stop(self) -> None: ...
    def recordings(self) -> Path: ...


class Embedded:
    """``crowdslam serve`` on a data directory (SQLite there, or ``database_url``), each building in a process
    of its own, started in a session of its own so that a kill takes its whole process group."""

    def __init__(self, root: Path, database_url: str | None = None) -> None:
        self.root = root
        self.env = {
            **os.environ,
            "CROWDSLAM_DATA_DIR": str(root),
            "CROWDSLAM_BUILDING_PROCESSES": "true",
            "CROWDSLAM_DEVICE_RATE_PER_S": "0",
            "CROWDSLAM_POSITION_HISTORY_DAYS": "0",
            "CROWDSLAM_SNAPSHOT_PERIOD_S": "2",
        }
        if database_url is not None:
            self.env["CROWDSLAM_DATABASE_URL"] = database_url
        self.operator = migrate_with_operator_key(self.env)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.process = self._start()

    def _start(self) -> subprocess.Popen[bytes]:
        log = self.root / "server.log"
        with log.open("ab") as sink:
            process = subprocess.Popen(
                [*CLI, "serve", "--host", "127.0.0.1", "--port", str(self.port)],
                env=self.env,
                stdout=sink,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

        def answers() -> bool:
            try:
                return httpx.get(f"{self.url}/healthz", timeout=1.0).status_code == 200
            except httpx.TransportError:
                return False

        return wait_until_ready(process, "crowdslam serve", log, answers, 120.0, poll_s=0.05)

    def building_processes(self) -> list[int]:
        return spawned_processes(self.root)

    def kill(self, target: Target) -> None:
        if target == "building":
            for pid in self.building_processes():
                os.kill(pid, signal.SIGKILL)
            return
        os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        deadline = time.monotonic() + 10.0  # a building's process dies with the server
        while self.building_processes() and time.monotonic() < deadline:
            time.sleep(0.02)
        self.process = self._start()

    def stop(self) -> None:
        """SIGTERM, as ``docker stop`` does: every building snapshots and closes its recording."""
        self.process.terminate()
        self.process.wait(timeout=120)

    def recordings(self) -> Path:
        return self.root / "recordings" / BUILDING

    def logs(self) -> str:
        return (self.root / "server.log").read_text()[-6000:]


class InCluster:
    """A cluster of one front and two workers on PostgreSQL and NATS (``tests.server.cluster.cluster``): a
    kill takes the worker holding the building, and a new worker joins in its place."""

    def __init__(self, cluster: Any) -> None:
        self.cluster = cluster
        self.url = cluster.front_urls()[0]
        self.operator = cluster.operator
        self.root = cluster.root

    def kill(self, target: Target) -> None:
        assert target == "worker"
        owner = self.cluster.owner_pids().get(BUILDING)
        victims = [p for p in self.cluster.workers if p.poll() is None and p.pid == owner]
        if not victims:  # nobody holds it at this instant (being taken over): the kill falls on a worker
            victims = [p for p in self.cluster.workers if p.poll() is None][:1]
        for process in victims:
            self.cluster.kill(process)
        self.cluster.start_worker()

    def stop(self) -> None:
        self.cluster.stop()

    def recordings(self) -> Path:
        return Path(self.cluster.root) / "recordings" / BUILDING

    def logs(self) -> str:
        return str(self.cluster.logs())


@dataclass
class Run:
    """What a run of the scenario answered and left."""

    receipts: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Each batch's first receipt, by batch id."""
    acknowledged: list[str] = field(default_factory=list)
    kills: list[dict[str, Any]] = field(default_factory=list)
    duplicates_checked: int = 0
    final: dict[str, Any] = field(default_factory=dict)
    recorded: list[str] = field(default_factory=list)
    seconds: float = 0.0


class Runner:
    def __init__(self, scenario: CrashScenario, server: Server, operator: str) -> None:
        self.scenario = scenario
        self.server = server
        self.operator = operator
        self.keys: dict[str, str] = {}
        self.prefixes: dict[str, str] = {}
        self.run = Run()

    # ------------------------------------------------------------------ requests
    def _client(self) -> httpx.Client:
        return httpx.Client(base_url=self.server.url, timeout=60.0)

    def _headers(self, who: str) -> dict[str, str]:
        key = self.operator if who == "operator" else self.keys[who]
        return {"Authorization": f"Bearer {key}", "Content-Type": "application/json"}

    def _path(self, step: Step) -> str:
        path = step.path
        for device, prefix in self.prefixes.items():
            path = path.replace(f"{{prefix of {device}}}", prefix)
        return path

    def _send(self, step: Step) -> httpx.Response:
        """One attempt (a lost connection raises ``httpx.TransportError``)."""
        body = (
            step.batch.model_dump_json(exclude_none=True)
            if step.batch is not None
            else (None if step.body is None else json.dumps(step.body))
        )
        with self._client() as client:
            return client.request(
                step.method, self._path(step), content=body, headers=self._headers(step.key)
            )

    def _until_answered(self, step: Step, after_crash: bool) -> httpx.Response:
        """Send until the server answers what the step expects (a 503 or a lost connection: again)."""
        allowed = step.ok | (step.again if after_crash else frozenset())
        deadline = time.monotonic() + RETRY_S
        while True:
            try:
                response = self._send(step)
            except httpx.TransportError:
                response = None
            if response is not None and response.status_code in allowed:
                return response
            if response is not None and response.status_code != 503:
                raise AssertionError(
                    f"{step.name}: answered {response.status_code} {response.text[:500]}\n{self._logs()}"
                )
            if time.monotonic() > deadline:
                raise AssertionError(f"{step.name}: not answered within {RETRY_S:.0f} s\n{self._logs()}")
            retry = 0.1 if response is None else min(float(response.headers.get("retry-after", 0.1)), 0.5)
            time.sleep(retry)

    def _logs(self) -> str:
        logs: Callable[[], str] | None = getattr(self.server, "logs", None)
        return "" if logs is None else logs()

    # ------------------------------------------------------------------ the scenario
    def setup(self) -> None:
        for step in self.scenario.setup:
            self._until_answered(step, after_crash=False)
        with self._client() as client:
            for device in self.scenario.devices:
                minted = client.post(
                    f"/v1/buildings/{BUILDING}/keys",
                    json={"scope": "device", "device_id": device},
                    headers=self._headers("operator"),
                )
                assert minted.status_code == 201, minted.text
                self.keys[device] = minted.json()["key"]
                self.prefixes[device] = minted.json()["prefix"]

    def play(self, kills: list[KillPoint]) -> Run:
        started = time.monotonic()
        self.setup()
        at = {k.step: k for k in kills}
        for i, step in enumerate(self.scenario.steps):
            kill = at.get(i)
            if kill is None:
                self._complete(step, self._until_answered(step, after_crash=False), after_crash=False)
                continue
            self._crash_in(step, kill)
        self._check_duplicates(self.run.acknowledged)
        self.run.final = self.state()
        self.server.stop()
        self.run.recorded = recorded_batches(self.server.recordings())
        self.run.seconds = time.monotonic() - started
        return self.run

    def _crash_in(self, step: Step, kill: KillPoint) -> None:
        """Send the step, kill the target ``kill.delay_s`` later, then send it until answered."""
        first: dict[str, Any] = {}

        def attempt() -> None:
            try:
                first["response"] = self._send(step)
            except httpx.TransportError as exc:
                first["error"] = repr(exc)

        thread = threading.Thread(target=attempt)
        thread.start()
        time.sleep(kill.delay_s)
        answered_before = not thread.is_alive()
        self.server.kill(kill.target)
        thread.join()
        response = first.get("response")
        if response is None or response.status_code not in step.ok:
            response = self._until_answered(step, after_crash=True)
        self._complete(step, response, after_crash=True)
        self.run.kills.append(
            {
                "step": kill.step,
                "name": step.name,
                "target": kill.target,
                "delay_ms": round(kill.delay_s * 1000, 1),
                "answered_before_the_kill": answered_before,
                "first_answer": first.get("error") or first["response"].status_code,
            }
        )
        self._check_duplicates(self.run.acknowledged[-RECENT:])
        health = self._get("/healthz")
        assert health["failing_buildings"] == [], health

    def _complete(self, step: Step, response: httpx.Response, after_crash: bool) -> None:
        if step.batch is not None:
            receipt = response.json()
            statuses = {"applied", "duplicate"} if after_crash else {"applied"}
            assert receipt["status"] in statuses, (step.name, receipt)
            self.run.receipts.setdefault(step.name, receipt)
            self.run.acknowledged.append(step.name)
        elif step.name == "signal map":
            self._built(response)

    def _built(self, response: httpx.Response) -> None:
        """Wait until the build is done and the building has loaded its radio map."""
        job = response.json()
        deadline = time.monotonic() + 300.0
        while True:
            job = self._get(f"/v1/buildings/{BUILDING}/signal-maps/{job['id']}")
            if job["status"] == "failed":
                raise AssertionError(f"the signal-map build failed: {job}")
            if job["status"] == "done" and job.get("radio_map_scans") is not None:
                return
            assert time.monotonic() < deadline, f"the signal map was not built and loaded: {job}"
            time.sleep(0.2)

    def _check_duplicates(self, batch_ids: list[str]) -> None:
        """Each acknowledged batch, sent again, answers ``duplicate`` (but a revoked phone's: its key)."""
        revoked = self.scenario.revoked
        for batch_id in batch_ids:
            batch = self.scenario.batches[batch_id]
            if batch.device_id == revoked:
                continue
            step = Step(batch_id, "POST", f"/v1/buildings/{BUILDING}/batches", batch.device_id, batch=batch)
            receipt = self._until_answered(step, after_crash=True).json()
            assert receipt["status"] == "duplicate", (batch_id, receipt)
            self.run.duplicates_checked += 1

    def _get(self, path: str) -> Any:
        deadline = time.monotonic() + RETRY_S
        while True:
            with self._client() as client:
                try:
                    response = client.get(path, headers=self._headers("operator"))
                except httpx.TransportError:
                    response = None
            if response is not None and response.status_code == 200:
                return response.json()
            assert time.monotonic() < deadline, f"GET {path}: {response and response.text}"
            time.sleep(0.1)

    def state(self) -> dict[str, Any]:
        """What the building holds, as its API tells it."""
        base = f"/v1/buildings/{BUILDING}"
        positions = sorted(self._get(f"{base}/positions"), key=lambda e: e["user_id"])
        histories = {
            e["user_id"]: self._get(f"{base}/users/{e['user_id']}/positions?limit=10000") for e in positions
        }
        keys = sorted(
            (k["scope"], k.get("device_id"), k.get("revoked_at") is not None)
            for k in self._get(f"{base}/keys")
        )
        zones = self._get(f"{base}/zones")
        visits = {z["id"]: self._get(f"{base}/zones/{z['id']}/visits") for z in zones}
        jobs = [
            {k: j.get(k) for k in ("status", "segments", "scans", "access_points", "radio_map_scans")}
            for j in self._get(f"{base}/signal-maps")
        ]
        zones = self._get(f"{base}/zones")
        visits = {z["id"]: self._get(f"{base}/zones/{z['id']}/visits") for z in zones}
        health = self._get("/healthz")
        return {
            "positions": positions,
            "anchors": sorted(self._get(f"{base}/anchors"), key=lambda a: a["id"]),
            "histories": histories,
            "keys": keys,
            "signal_maps": jobs,
            "zones": zones,
            "visits": visits,
            "failing_buildings": health["failing_buildings"],
        }


def recorded_batches(folder: Path) -> list[str]:
    """The ids of the batches in a building's recordings, each once."""
    found = set()
    for path in sorted(folder.glob("*.mcap")):
        for recorded in read_batches(path):
            found.add(json.loads(recorded.raw)["batch_id"])
    return sorted(found)


def differences(reference: Run, crashed: Run) -> list[str]:
    """Where the crashed run's outcome differs from the reference's (empty: a crash changed nothing)."""
    found = []
    compared = 0
    for batch_id, receipt in crashed.receipts.items():
        if receipt["status"] != "applied":
            continue  # applied before the crash, its first answer lost: its receipt now is a duplicate's
        expected = reference.receipts[batch_id]
        for name in ("estimate", "tracking", "encounters", "warnings"):
            if receipt.get(name) != expected.get(name):
                found.append(f"receipt of {batch_id}: {name} {receipt.get(name)} != {expected.get(name)}")
        compared += 1
    if compared < len(reference.receipts) // 2:
        found.append(f"only {compared} receipts compared of {len(reference.receipts)}")
    for name, value in reference.final.items():
        if crashed.final.get(name) != value:
            found.append(f"{name}: {_short(crashed.final.get(name))} != {_short(value)}")
    if crashed.final.get("failing_buildings"):
        found.append(f"failing buildings: {crashed.final['failing_buildings']}")
    if crashed.recorded != reference.recorded:
        missing = sorted(set(reference.recorded) - set(crashed.recorded))
        extra = sorted(set(crashed.recorded) - set(reference.recorded))
        found.append(f"recordings: missing {missing[:10]} ({len(missing)}), extra {extra[:10]}")
    return found


def _short(value: Any) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) < 400 else text[:400] + "..."


@contextmanager
def embedded(root: Path, database_url: str | None = None) -> Iterator[Embedded]:
    server = Embedded(root, database_url)
    try:
        yield server
    finally:
        if server.process.poll() is None:
            os.killpg(server.process.pid, signal.SIGKILL)
            server.process.wait()


def play(scenario: CrashScenario, server: Embedded | InCluster, kills: list[KillPoint]) -> Run:
    return Runner(scenario, server, server.operator).play(kills)
