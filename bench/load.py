"""Load benchmark: a real server on loopback, N virtual phones posting one batch per second each, and live
dashboards on the WebSocket.

    python bench/load.py [--phones 250,500,1000,2000] [--duration 30] [--dashboards 10] [--buildings 1]
                         [--postgres URL] [--cluster FRONTS,WORKERS [--nats URL]] [--json OUT]

For each N (ascending) a fresh server (``crowdslam serve``, SQLite, recording on: the defaults a newcomer
gets; with ``--postgres``, a new database on that PostgreSQL server) is started in its own process. Each
phone starts with a position fix, then posts every second: two steps (1.4 m/s, azimuth given), a WiFi scan
every 2 s (15 strongest of 60 access points, log-distance path loss with 4 dB noise) and Bluetooth sightings
of the phones within 8 m. Phones are spread evenly over each second, and their scans over every two (phones
do not scan in step), so the offered load is N batches per second, half of them with a scan.

The phones walk in during the first half of the warm-up (``_warmup_s``), evenly, as people enter a
building; the second half lets the server settle before the measured window. (Admitting every phone in
the same second is a burst of its own: a new user costs ~1 ms, several times a batch, and at 1,700 phones
the backlog of that second took 8 s to drain. ``bench/building.py`` reports it as
``admit_us_per_phone``.)

Latency runs from the moment a post was due to its answer (a request queued behind a slow one counts its
wait). ``ws_lag`` runs from a batch's last step to the dashboard receiving that position; the dashboards
run in a process of their own and count the measured window only. The load generator
shares the machine with the server: it speaks HTTP/1.1 over a pool of keep-alive sockets with pre-formatted
bodies so that it costs little next to the server.

Prints one JSON object: per-N rows (``phones, batches_per_s, p50_ms, p99_ms, ws_lag_p99_ms, errors``, and
the server's CPU time per batch and cores used, split into its front's and its building processes' cores,
and the generator's cores, from /proc over the measured window: the steadiest figure of what a change
costs; ``p50_ms_per_second``: the median latency of each measured second, which shows whether a backlog
drains) and ``sustained``: the largest N with p99 <= 100 ms, the offered rate met within 5 % and no
errors.

With ``--cluster FRONTS,WORKERS`` (and ``--postgres``), each N runs on a cluster instead: a private
``nats-server -js`` (or the one at ``--nats``; building ids then carry the run's prefix), that many
``crowdslam serve --role worker`` and ``--role front`` processes on a new database; the phones' connections
and the dashboards are dealt round the fronts. The rows then split the CPU per batch and the cores by role:
fronts, workers, NATS and PostgreSQL (every ``postgres`` process of the machine), and give their sum,
``cluster_cpu_ms_per_batch``; the single process serves the same load on the same PostgreSQL first, and
``cpu_vs_single_process`` is the ratio of the two costs (server and PostgreSQL).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import multiprocessing
import os
import re
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from server.engine.numba_cache import configure_numba_cache

configure_numba_cache()

from report import emit
from websockets.asyncio.client import connect

from schemas.api import KeyScope
from server.auth import mint_key
from server.cli.background_server import free_port, serve_process
from server.cli.local_cluster import nats_server, postgres_database, worker_process
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade
from server.store.models import BuildingRow

FLOOR_M = (120.0, 80.0)
N_APS = 60
SCAN_TOP = 15
BLUETOOTH_RANGE_M = 8.0
P99_TARGET_MS = 100.0


@dataclass
class Crowd:
    """The virtual phones' true state, advanced once per second."""

    rng: np.random.Generator
    xy: np.ndarray
    azimuth: np.ndarray  # clockwise from north
    aps: np.ndarray

    @classmethod
    def create(cls, n: int, seed: int) -> Crowd:
        rng = np.random.default_rng(seed)
        xy = rng.uniform((5.0, 5.0), (FLOOR_M[0] - 5.0, FLOOR_M[1] - 5.0), size=(n, 2))
        aps = rng.uniform((0.0, 0.0), FLOOR_M, size=(N_APS, 2))
        return cls(rng, xy, rng.uniform(-math.pi, math.pi, n), aps)

    def walk(self) -> None:
        self.azimuth += self.rng.normal(0.0, 0.2, self.azimuth.size)
        step = 1.4 * np.column_stack([np.sin(self.azimuth), np.cos(self.azimuth)])
        nxt = self.xy + step
        out = (nxt < 1.0) | (nxt > np.array(FLOOR_M) - 1.0)
        bounce: np.ndarray = np.asarray(out.any(axis=1), dtype=bool)
        self.azimuth[bounce] += math.pi
        self.xy = np.where(bounce[:, None], self.xy, nxt)

    def scan(self, phone: int) -> tuple[np.ndarray, np.ndarray]:
        d = np.hypot(*(self.aps - self.xy[phone]).T)
        rss = -40.0 - 25.0 * np.log10(np.maximum(d, 1.0)) + self.rng.normal(0.0, 4.0, N_APS)
        top = np.argsort(-rss)[:SCAN_TOP]
        return top, np.clip(rss[top], -99.0, -20.0)

    def neighbours(self) -> list[np.ndarray]:
        """Up to three phones within Bluetooth range of each phone, the nearest cells' first (a grid, not an
        N x N matrix; plain floats: the generator shares the machine with the server)."""
        keys = np.floor(self.xy / BLUETOOTH_RANGE_M).astype(int).tolist()
        cells: dict[tuple[int, int], list[int]] = {}
        for i, (cx, cy) in enumerate(keys):
            cells.setdefault((cx, cy), []).append(i)
        xy = self.xy.tolist()
        result = []
        for i, (cx, cy) in enumerate(keys):
            x, y = xy[i]
            near: list[int] = []
            for dx, dy in _AROUND:
                for j in cells.get((cx + dx, cy + dy), ()):
                    if j != i and math.hypot(xy[j][0] - x, xy[j][1] - y) <= BLUETOOTH_RANGE_M:
                        near.append(j)
                if len(near) >= 3:
                    break
            result.append(np.array(near[:3], dtype=int))
        return result


_AROUND = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]


def _building(phone: int, buildings: int, prefix: str = "") -> str:
    """Phones are dealt round the buildings; one building is called ``load`` (``prefix``: a cluster run's,
    so that a NATS server kept between runs never hands one run's batches to the next)."""
    return prefix + ("load" if buildings == 1 else f"load-{phone % buildings}")


_AP_JSON = [f'{{"bssid":"02:00:00:00:00:{a:02x}","rssi_dbm":' for a in range(N_APS)]
"""Each access point's entry up to its RSSI: the generator shares the machine with the server."""


def _body(crowd: Crowd, phone: int, seq: int, now_ms: int, near: np.ndarray, building: str) -> bytes:
    device = f"load-{phone:05d}"
    parts = [
        f'{{"building_id":"{building}","device_id":"{device}","batch_id":"{device}-{seq}","seq":{seq},'
        f'"ble_advertised_id":"ble-{phone:05d}"'
    ]
    x, y = crowd.xy[phone].tolist()
    az = float(crowd.azimuth[phone])
    az = (az + math.pi) % (2 * math.pi) - math.pi
    if seq == 0:
        parts.append(
            f',"landmarks":[{{"kind":"fix","t_ms":{now_ms - 990},"position":{{"x_m":{x:.2f},"y_m":{y:.2f}}},'
            f'"sigma_m":1.0,"azimuth_rad":{az:.4f}}}]'
        )
    parts.append(
        f',"steps":[{{"t_ms":{now_ms - 500},"length_m":0.7,"azimuth_rad":{az:.4f}}},'
        f'{{"t_ms":{now_ms},"length_m":0.7,"azimuth_rad":{az:.4f}}}]'
    )
    if (seq + phone) % 2 == 0:  # every 2 s, half of the phones each second
        top, rss = crowd.scan(phone)
        entries = zip(top.tolist(), rss.tolist(), strict=True)
        aps = ",".join(f'{_AP_JSON[a]}{r:.1f},"frequency_mhz":2437}}' for a, r in entries)
        parts.append(f',"wifi_scans":[{{"t_ms":{now_ms - 200},"aps":[{aps}]}}]')
    if near.size:
        sightings = ",".join(
            f'{{"kind":"peer","t_ms":{now_ms - 100},"peer_advertised_id":"ble-{j:05d}",'
            f'"rssi_dbm":{-60.0 - 3.0 * math.hypot(xj - x, yj - y):.1f}}}'
            for j, (xj, yj) in zip(near.tolist(), crowd.xy[near].tolist(), strict=True)
        )
        parts.append(f',"bluetooth":[{sightings}]')
    parts.append("}")
    return "".join(parts).encode()


def _warmup_s(duration_s: float) -> float:
    """The first seconds of a run are not measured (connections open, the building loads, the phones walk
    in during the first half)."""
    return float(min(10, math.floor(duration_s / 3)))  # whole seconds: the measured window is too


def _join_second(n: int, duration_s: float) -> np.ndarray:
    """The second each phone walks in (sends its fix): evenly over the first half of the warm-up."""
    ramp_s = max(1, math.floor(_warmup_s(duration_s) / 2))
    return (np.arange(n) * ramp_s) // max(n, 1)


class Connection:
    """One keep-alive HTTP/1.1 connection; requests on it run one at a time."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, port: int) -> None:
        self.reader, self.writer = reader, writer
        self.port = port

    @classmethod
    async def open(cls, port: int) -> Connection:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        return cls(reader, writer, port)

    async def post(self, path: str, key: str, body: bytes) -> int:
        head = (
            f"POST {path} HTTP/1.1\r\nHost: load\r\nAuthorization: Bearer {key}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
        ).encode()
        self.writer.write(head + body)
        status_line = await self.reader.readline()
        length = 0
        while True:
            line = await self.reader.readline()
            if line in (b"\r\n", b""):
                break
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"content-length":
                length = int(value)
        await self.reader.readexactly(length)
        parts = status_line.split()
        return int(parts[1]) if len(parts) > 1 else 0


@dataclass
class Results:
    latencies_ms: list[float] = field(default_factory=list)
    due_s: list[int] = field(default_factory=list)
    """The second of the run each measured post was due in (beside its latency)."""
    ws_lag_ms: list[float] = field(default_factory=list)
    errors: int = 0
    sent: int = 0
    dashboard_errors: list[str] = field(default_factory=list)
    cpu_s: dict[str, float] = field(default_factory=dict)
    """CPU seconds (user + system) each measured part of the server used while the measured batches were
    due (``Meters``)."""
    generator_cpu_s: float = math.nan
    dashboards_cpu_s: float = math.nan
    measured_wall_s: float = math.nan


Meters = dict[str, Callable[[], float]]
"""What the server's CPU is counted by: each part's cumulative CPU seconds."""


def _cpu_of(pids: list[int], children: bool = False) -> float:
    return sum(_cpu_seconds(pid, children) for pid in pids)


def _postgres_cpu_seconds() -> float:
    """Every PostgreSQL process on this machine (its backends serve the cluster's fronts and workers)."""
    total = 0.0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        if text.split("(", 1)[1].startswith("postgres)"):
            fields = text.rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def _cpu_seconds(pid: int, children: bool = False) -> float:
    """User + system CPU time of a process, and of its children when asked (the server's building
    processes): Linux /proc; NaN elsewhere."""
    total = math.nan
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(stat.parent.name) == pid or (children and int(fields[1]) == pid):
            total = (0.0 if math.isnan(total) else total) + (int(fields[11]) + int(fields[12])) / os.sysconf(
                "SC_CLK_TCK"
            )
    return total


_POSITION = re.compile(
    r'"type":"position","estimate":\{"building_id":"[^"]*","user_id":"([^"]*)","device_id":"[^"]*","t_ms":(\d+)'
)
"""A position message's user and time, read off the frame's text: ten dashboards parsing every frame with
``json`` took ~0.25 of a core beside the server (real dashboards run elsewhere); a frame whose positions do
not all match (the estimate's fields reordered) is counted as an error, not skipped."""


async def _dashboard(url: str, lags: list[float], since_ms: float, stop: asyncio.Event) -> None:
    # an encounter re-publishes the peer's estimate with the peer's older time: count each (user, time) once,
    # so the lag is from a batch's last step to the first position it produced
    seen: set[tuple[str, int]] = set()
    async with connect(url, max_size=None) as ws:
        while not stop.is_set():
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=0.5)
            except TimeoutError:
                continue
            received = time.time() * 1000.0
            assert isinstance(frame, str)
            found = _POSITION.findall(frame)
            if len(found) != frame.count('"type":"position"'):
                raise ValueError(f"a position message not in the expected form: {frame[:200]}")
            for user, t in found:
                key = (user, int(t))
                if key[1] >= since_ms and key not in seen:
                    seen.add(key)
                    lags.append(received - key[1])


def _dashboards(urls: list[str], n: int, since_ms: float, stop: Any, out: Any) -> None:
    """The dashboards, in a process of their own so that reading frames does not wait behind the phones'
    requests in one event loop (which read as live lag); sends back (lags, errors) when ``stop`` is set."""

    async def run() -> tuple[list[float], list[str]]:
        lags: list[float] = []
        done = asyncio.Event()
        tasks = [asyncio.create_task(_dashboard(urls[k % len(urls)], lags, since_ms, done)) for k in range(n)]
        while not stop.is_set():
            await asyncio.sleep(0.2)
        done.set()
        outcomes = await asyncio.gather(*tasks, return_exceptions=True)
        return lags, [repr(o) for o in outcomes if isinstance(o, Exception)]

    out.send(asyncio.run(run()))


async def _drive(
    ports: list[int],
    keys: list[str],
    dashboard_keys: list[str],
    duration_s: float,
    n_dashboards: int,
    connections: int,
    meters: Meters,
    prefix: str = "",
) -> Results:
    """The phones' connections are dealt round the ``ports`` (a cluster's fronts), the dashboards too."""
    n = len(keys)
    crowd = Crowd.create(n, seed=0)
    results = Results()
    pool: asyncio.Queue[Connection] = asyncio.Queue()
    for k in range(min(connections, n)):
        pool.put_nowait(await Connection.open(ports[k % len(ports)]))
    buildings = len(dashboard_keys)
    lives = [
        f"ws://127.0.0.1:{ports[b % len(ports)]}/v1/buildings/{_building(b, buildings, prefix)}/live"
        f"?token={key}&batch=true"
        for b, key in enumerate(dashboard_keys)
    ]
    context = multiprocessing.get_context("spawn")
    stop, (receive_lags, send_lags) = context.Event(), context.Pipe(duplex=False)
    since_ms = (time.time() + 0.5 + _warmup_s(duration_s)) * 1000.0
    dashboards = context.Process(target=_dashboards, args=(lives, n_dashboards, since_ms, stop, send_lags))
    dashboards.start()
    await asyncio.sleep(0.5)
    phase = np.linspace(0.0, 1.0, n, endpoint=False)
    building_of = np.arange(n) % buildings
    near: list[np.ndarray] = []

    def bodies(phone: int, seq: int, now_ms: int) -> bytes:
        # a phone hears the phones near it in its own building only
        heard = near[phone][building_of[near[phone]] == building_of[phone]]
        return _body(crowd, phone, seq, now_ms, heard, _building(phone, buildings, prefix))

    tasks: set[asyncio.Task[None]] = set()
    warmup_s = _warmup_s(duration_s)

    async def send(phone: int, seq: int, due: float, body: bytes, measure: bool) -> None:
        conn = await pool.get()
        try:
            status = await conn.post(
                f"/v1/buildings/{_building(phone, buildings, prefix)}/batches", keys[phone], body
            )
        except (ConnectionError, asyncio.IncompleteReadError):
            results.errors += 1
            conn = await Connection.open(conn.port)
        else:
            if status != 200:
                results.errors += 1
            elif measure:
                results.latencies_ms.append((time.perf_counter() - due) * 1000.0)
                results.due_s.append(int(due - start))
        finally:
            pool.put_nowait(conn)

    joins = _join_second(n, duration_s)
    start = time.perf_counter()
    second = 0
    while second < duration_s:
        crowd.walk()
        near = crowd.neighbours()  # read by bodies()
        base = start + second
        measure = second >= warmup_s
        if second == math.ceil(warmup_s):
            cpu_at = (
                {part: meter() for part, meter in meters.items()},
                _cpu_seconds(os.getpid()),
                time.perf_counter(),
                _cpu_seconds(dashboards.pid or 0),
            )
        for phone in np.argsort(phase):
            seq = second - int(joins[phone])
            if seq < 0:  # not in the building yet
                continue
            due = base + phase[phone]
            delay = due - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            now_ms = int(time.time() * 1000)
            task = asyncio.create_task(send(int(phone), seq, due, bodies(int(phone), seq, now_ms), measure))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
            results.sent += measure
        second += 1
    if tasks:
        await asyncio.wait(tasks, timeout=30.0)
    results.cpu_s = {part: meter() - cpu_at[0][part] for part, meter in meters.items()}
    results.generator_cpu_s = _cpu_seconds(os.getpid()) - cpu_at[1]
    results.measured_wall_s = time.perf_counter() - cpu_at[2]
    results.dashboards_cpu_s = _cpu_seconds(dashboards.pid or 0) - cpu_at[3]
    stop.set()
    results.ws_lag_ms, results.dashboard_errors = receive_lags.recv()
    dashboards.join(timeout=30.0)
    while not pool.empty():
        pool.get_nowait().writer.close()
    return results


@contextlib.contextmanager
def _database(data_dir: Path, postgres: str | None) -> Iterator[str]:
    """The run's database: SQLite in its data folder (the default), or with ``postgres`` (a server URL
    whose databases the bench may create and drop) a new database on that server, dropped after the run."""
    if postgres is None:
        yield f"sqlite:///{data_dir / 'crowdslam.sqlite3'}"
        return
    with postgres_database(postgres, prefix="crowdslam_load") as url:
        yield url


def _prepare(database_url: str, n: int, buildings: int, prefix: str = "") -> tuple[list[str], list[str]]:
    """The buildings, a device key per phone (for its building) and a dashboard key per building."""
    engine = make_engine(database_url)
    upgrade(engine)
    with make_session_factory(engine).begin() as session:
        for b in range(buildings):
            session.add(BuildingRow(id=_building(b, buildings, prefix), name="Load test", rotation_rad=0.0))
        session.flush()
        keys = [
            mint_key(session, KeyScope.DEVICE, _building(i, buildings, prefix), f"load-{i:05d}")[0]
            for i in range(n)
        ]
        dashboards = [
            mint_key(session, KeyScope.DASHBOARD, _building(b, buildings, prefix))[0]
            for b in range(buildings)
        ]
    engine.dispose()
    return keys, dashboards


def run_one(
    n: int,
    duration_s: float,
    n_dashboards: int,
    connections: int,
    buildings: int = 1,
    postgres: str | None = None,
) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp, _database(Path(tmp), postgres) as database_url:
        data_dir = Path(tmp)
        keys, dashboards = _prepare(database_url, n, buildings)
        port = free_port()
        env = {**os.environ, "CROWDSLAM_DATA_DIR": str(data_dir), "CROWDSLAM_DATABASE_URL": database_url}
        server = serve_process(env, port, data_dir / "server.log", log_level="warning")
        pid = server.pid
        meters: Meters = {
            "server": lambda: _cpu_seconds(pid, children=True),
            "front": lambda: _cpu_seconds(pid),
        }
        if postgres is not None:
            meters["postgresql"] = _postgres_cpu_seconds
        try:
            started = time.perf_counter()
            results = asyncio.run(
                _drive([port], keys, dashboards, duration_s, n_dashboards, connections, meters)
            )
            elapsed = time.perf_counter() - started
        finally:
            server.terminate()
            server.wait(timeout=60)
    row = _row(n, buildings, "sqlite" if postgres is None else "postgresql", duration_s, results, elapsed)
    cpu, wall = results.cpu_s, results.measured_wall_s
    row |= {
        "server_cpu_ms_per_batch": round(1e3 * cpu["server"] / max(results.sent, 1), 3),
        "server_cores": round(cpu["server"] / wall, 2),
        "front_cores": round(cpu["front"] / wall, 2),
        "building_cores": round((cpu["server"] - cpu["front"]) / wall, 2),
    }
    if "postgresql" in cpu:
        row["postgresql_cpu_ms_per_batch"] = round(1e3 * cpu["postgresql"] / max(results.sent, 1), 3)
        row["postgresql_cores"] = round(cpu["postgresql"] / wall, 2)
    return row


def run_cluster(
    n: int,
    duration_s: float,
    n_dashboards: int,
    connections: int,
    buildings: int,
    postgres: str,
    fronts: int,
    workers: int,
    nats_url: str | None,
) -> dict[str, Any]:
    """One run on a cluster of ``fronts`` and ``workers`` processes, on a new database and on the NATS at
    ``nats_url`` (default: a private ``nats-server -js`` started for the run)."""
    prefix = f"r{os.getpid()}-{time.monotonic_ns() % 10**8}-"
    with tempfile.TemporaryDirectory() as tmp, postgres_database(postgres, prefix="crowdslam_load") as url:
        data_dir = Path(tmp)
        keys, dashboards = _prepare(url, n, buildings, prefix)
        with contextlib.ExitStack() as stack:
            nats_pids: list[int] = []
            if nats_url is None:
                nats_port = free_port()
                nats = nats_server(nats_port, data_dir / "nats", data_dir / "nats.log")
                stack.callback(nats.wait, 30)
                stack.callback(nats.terminate)
                nats_url = f"nats://127.0.0.1:{nats_port}"
                nats_pids = [nats.pid]
            else:
                nats_pids = _pids_named("nats-server")
            env = {
                **os.environ,
                "CROWDSLAM_DATA_DIR": str(data_dir),
                "CROWDSLAM_DATABASE_URL": url,
                "CROWDSLAM_NATS_URL": nats_url,
            }
            worker_pids, front_pids, ports = [], [], []
            for k in range(workers):
                process = worker_process(env, data_dir / f"worker-{k}.log")
                stack.callback(_stop, process)
                worker_pids.append(process.pid)
            for k in range(fronts):
                port = free_port()
                process = serve_process(
                    {**env, "CROWDSLAM_ROLE": "front"}, port, data_dir / f"front-{k}.log", log_level="warning"
                )
                stack.callback(_stop, process)
                front_pids.append(process.pid)
                ports.append(port)
            meters: Meters = {
                "fronts": lambda: _cpu_of(front_pids),
                "workers": lambda: _cpu_of(worker_pids),
                "nats": lambda: _cpu_of(nats_pids),
                "postgresql": _postgres_cpu_seconds,
            }
            started = time.perf_counter()
            results = asyncio.run(
                _drive(ports, keys, dashboards, duration_s, n_dashboards, connections, meters, prefix)
            )
            elapsed = time.perf_counter() - started
    row = _row(n, buildings, "postgresql", duration_s, results, elapsed)
    row["cluster"] = {"fronts": fronts, "workers": workers}
    total = sum(results.cpu_s.values())
    row["cluster_cpu_ms_per_batch"] = round(1e3 * total / max(results.sent, 1), 3)
    row["cluster_cores"] = round(total / results.measured_wall_s, 2)
    for part, seconds in results.cpu_s.items():
        row[f"{part}_cpu_ms_per_batch"] = round(1e3 * seconds / max(results.sent, 1), 3)
        row[f"{part}_cores"] = round(seconds / results.measured_wall_s, 2)
    return row


def _stop(process: Any) -> None:
    process.terminate()
    try:
        process.wait(timeout=60)
    except Exception:
        process.kill()


def _pids_named(name: str) -> list[int]:
    found = []
    for comm in Path("/proc").glob("[0-9]*/comm"):
        with contextlib.suppress(OSError):
            if comm.read_text().strip() == name:
                found.append(int(comm.parent.name))
    return found


def _row(
    n: int, buildings: int, database: str, duration_s: float, results: Results, elapsed: float
) -> dict[str, Any]:
    lat = np.array(results.latencies_ms) if results.latencies_ms else np.array([math.inf])
    lag = np.array(results.ws_lag_ms) if results.ws_lag_ms else np.array([math.inf])
    measured_s = duration_s - _warmup_s(duration_s)
    return {
        "phones": n,
        "buildings": buildings,
        "database": database,
        "offered_per_s": n,
        "batches_per_s": round(len(results.latencies_ms) / measured_s, 1),
        "p50_ms": round(float(np.percentile(lat, 50)), 1),
        "p99_ms": round(float(np.percentile(lat, 99)), 1),
        "ws_lag_p50_ms": round(float(np.percentile(lag, 50)), 1),
        "ws_lag_p99_ms": round(float(np.percentile(lag, 99)), 1),
        "p50_ms_per_second": _p50_per_second(results),
        "ws_positions": len(results.ws_lag_ms),
        "errors": results.errors + len(results.dashboard_errors),
        "generator_cores": round(results.generator_cpu_s / results.measured_wall_s, 2),
        "dashboards_cores": round(results.dashboards_cpu_s / results.measured_wall_s, 2),
        "dashboard_errors": results.dashboard_errors[:3],
        "seconds": round(elapsed, 1),
    }


def _p50_per_second(results: Results) -> list[float]:
    """Median latency of the posts due in each measured second: a backlog that drains falls along it, one
    that the server never catches up on (the load at or above capacity) stays."""
    if not results.latencies_ms:
        return []
    second = np.array(results.due_s)
    lat = np.array(results.latencies_ms)
    return [round(float(np.median(lat[second == s])), 1) for s in np.unique(second)]


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--phones", default="250,500,1000,2000", help="comma-separated phone counts")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of load per phone count")
    parser.add_argument("--dashboards", type=int, default=10)
    parser.add_argument(
        "--buildings", type=int, default=1, help="phones dealt round this many buildings (dashboards too)"
    )
    parser.add_argument(
        "--connections", type=int, default=256, help="keep-alive sockets shared by the phones"
    )
    parser.add_argument(
        "--postgres",
        metavar="URL",
        help="serve from PostgreSQL instead of SQLite: each run in a new database on this server (e.g. "
        "postgresql+psycopg://postgres@127.0.0.1:5432/test), dropped after it",
    )
    parser.add_argument(
        "--cluster",
        metavar="FRONTS,WORKERS",
        help="serve from a cluster of this many fronts and workers (needs --postgres); the phones' "
        "connections and the dashboards are dealt round the fronts",
    )
    parser.add_argument(
        "--nats", metavar="URL", help="the cluster's NATS (default: a private nats-server -js per run)"
    )
    parser.add_argument("--json", type=Path, help="also write the result here")
    args = parser.parse_args()
    cluster = None
    if args.cluster is not None:
        try:
            fronts, workers = (int(x) for x in args.cluster.split(","))
        except ValueError:
            parser.error("--cluster takes FRONTS,WORKERS, e.g. 2,2")
        if fronts < 1 or workers < 1:
            parser.error("--cluster needs at least one front and one worker")
        if args.postgres is None:
            parser.error("--cluster needs --postgres (a cluster shares one PostgreSQL)")
        cluster = (fronts, workers)
    rows = []
    for n in sorted(int(p) for p in args.phones.split(",")):
        if cluster is None:
            row = run_one(n, args.duration, args.dashboards, args.connections, args.buildings, args.postgres)
        else:
            # the single process on the same PostgreSQL first: the cluster's cost is a ratio to it
            single = run_one(
                n, args.duration, args.dashboards, args.connections, args.buildings, args.postgres
            )
            print(json.dumps(single), file=sys.stderr)
            row = run_cluster(
                n,
                args.duration,
                args.dashboards,
                args.connections,
                args.buildings,
                args.postgres,
                *cluster,
                args.nats,
            )
            one = single["server_cpu_ms_per_batch"] + single["postgresql_cpu_ms_per_batch"]
            row["single_process"] = {
                k: single[k]
                for k in (
                    "p50_ms",
                    "p99_ms",
                    "errors",
                    "server_cpu_ms_per_batch",
                    "postgresql_cpu_ms_per_batch",
                )
            }
            row["cpu_vs_single_process"] = round(row["cluster_cpu_ms_per_batch"] / one, 2)
        print(json.dumps(row), file=sys.stderr)
        rows.append(row)
    ok = [
        r["phones"]
        for r in rows
        if r["p99_ms"] <= P99_TARGET_MS
        and r["errors"] == 0
        and r["batches_per_s"] >= 0.95 * r["offered_per_s"]
    ]
    best = max(ok, default=0)
    sustained = next((r for r in rows if r["phones"] == best), None)
    result = {
        "benchmark": "load",
        "machine_cores": os.cpu_count(),
        "duration_s": args.duration,
        "dashboards": args.dashboards,
        "p99_target_ms": P99_TARGET_MS,
        "sustained": sustained,
        "rows": rows,
    }
    emit(result, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
