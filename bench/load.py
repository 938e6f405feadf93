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
shares the machine with the server: it speaks HTTP/1.1 over a pool of keep-alive sockets, and formats every
body before the run (each timed at the moment it will be due; a run of more than ``PREFORMAT_MAX`` batches
formats them as they are due), so that it costs little next to the server.

Prints one JSON object: per-N rows (``phones, batches_per_s, p50_ms, p99_ms, ws_lag_p99_ms, errors``, and
the server's CPU time per batch and cores used, split into its front's and its building processes' cores,
and the generator's cores, from /proc over the measured window: the steadiest figure of what a change
costs; the same as each process's CPU microseconds a batch: ``front_us_per_batch``,
``building_us_per_batch``, ``generator_us_per_batch``; ``p50_ms_per_second``: the median latency of each
measured second, which shows whether a backlog drains, and ``p99_ms_per_second``, which shows whether
the p99 is a few seconds' spikes or a broad tail)
and ``sustained``: the largest N with p99 <= 100 ms, the offered rate met within 5 % and no errors.

With ``--cluster FRONTS,WORKERS`` (and ``--postgres``), each N runs on a cluster instead: a private
``nats-server -js`` (or the one at ``--nats``; building ids then carry the run's prefix), that many
``crowdslam serve --role worker`` and ``--role front`` processes on a new database; the phones' connections
and the dashboards are dealt round the fronts. The rows then split the CPU per batch and the cores by role:
fronts, workers, NATS and PostgreSQL (every ``postgres`` process of the machine), and give their sum,
``cluster_cpu_ms_per_batch``; the single process serves the same load on the same PostgreSQL first, and
``cpu_vs_single_process`` is the ratio of the two costs (server and PostgreSQL).

With ``--soak SECONDS`` (and a long ``--duration``), every SECONDS the run samples the resident memory of
each process (the server's front, each building process, this generator, the dashboards' process) and the
disk the server takes (its data directory, the recordings, the database), and reports each series' slope
per minute after ``--soak-warmup`` and the bytes each batch costs on disk; ``--plot`` draws them.
``--server-env CROWDSLAM_...=...`` changes a setting of the server's (shorter retention windows show the
database level off within a run). ``--keep-recordings DIR`` keeps the recordings for a replay.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import copy
import json
import math
import multiprocessing
import os
import re
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from server.slam.numba_cache import configure_numba_cache

configure_numba_cache()

from report import emit
from websockets.asyncio.client import connect

from schemas.api import KeyScope
from server.auth import mint_key
from server.cli.background_server import free_port, serve_process
from server.cli.local_cluster import nats_server, postgres_database, worker_process
from server.storage import database_bytes, tree_bytes
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


PREFORMAT_MAX = 200_000
"""Bodies formatted before a run (~1 KB each) when the run posts at most this many; a longer run (a soak)
formats each as it is due."""


def _warmup_s(duration_s: float) -> float:
    """The first seconds of a run are not measured (connections open, the building loads, the phones walk
    in during the first half)."""
    return float(min(10, math.floor(duration_s / 3)))  # whole seconds: the measured window is too


def _join_second(n: int, duration_s: float) -> np.ndarray:
    """The second each phone walks in (sends its fix): evenly over the first half of the warm-up."""
    ramp_s = max(1, math.floor(_warmup_s(duration_s) / 2))
    return (np.arange(n) * ramp_s) // max(n, 1)


class Posts:
    """The phones' posts over a pool of keep-alive HTTP/1.1 connections, on callbacks rather than a task, a
    stream reader and a queue hand-off each (those had cost the generator ~100 us of CPU a post, on the
    cores it shares with the server): a post waits in ``pending`` until a connection is free, each
    connection holds one request at a time, and its answer (status line, ``Content-Length``, body) is read
    off the bytes as they arrive. ``done(status, due, measured)`` is called for every post: status 0 for
    one whose connection failed (the connection is opened again)."""

    def __init__(self, ports: list[int], size: int, done: Callable[[int, float, bool], None]) -> None:
        self.ports = ports
        self.size = size
        self.done = done
        self.free: list[_Link] = []
        self.pending: collections.deque[tuple[bytes, float, bool]] = collections.deque()
        self.links: list[_Link] = []

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        for k in range(self.size):
            port = self.ports[k % len(self.ports)]
            _, link = await loop.create_connection(lambda port=port: _Link(self, port), "127.0.0.1", port)
            self.links.append(link)
            self.free.append(link)

    def post(self, path: str, key: str, body: bytes, due: float, measured: bool) -> None:
        request = (
            f"POST {path} HTTP/1.1\r\nHost: load\r\nAuthorization: Bearer {key}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
        ).encode() + body
        if self.free:
            self.free.pop().send(request, due, measured)
        else:
            self.pending.append((request, due, measured))

    def ready(self, link: _Link) -> None:
        """``link`` is free: it takes the oldest waiting post."""
        if self.pending:
            link.send(*self.pending.popleft())
        else:
            self.free.append(link)

    def reopen(self, link: _Link) -> None:
        async def again() -> None:
            _, fresh = await asyncio.get_running_loop().create_connection(
                lambda: _Link(self, link.port), "127.0.0.1", link.port
            )
            self.links.append(fresh)
            self.ready(fresh)

        asyncio.get_running_loop().create_task(again())

    def close(self) -> None:
        links, self.links = self.links, []  # closed on purpose: none is opened again
        for link in links:
            if link.transport is not None:
                link.transport.close()


class _Link(asyncio.Protocol):
    """One connection of ``Posts``."""

    def __init__(self, posts: Posts, port: int) -> None:
        self.posts = posts
        self.port = port
        self.transport: asyncio.Transport | None = None
        self.buffer = bytearray()
        self.started: tuple[float, bool] | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # uvloop's transports are not its subclasses

    def send(self, request: bytes, due: float, measured: bool) -> None:
        assert self.transport is not None
        self.started = (due, measured)
        self.transport.write(request)

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        end = self.buffer.find(b"\r\n\r\n")
        if end < 0:
            return
        head = bytes(self.buffer[:end]).lower()
        length = 0
        at = head.find(b"content-length:")
        if at >= 0:
            line_end = head.find(b"\r\n", at)
            length = int(head[at + 15 : line_end if line_end >= 0 else len(head)])
        if len(self.buffer) < end + 4 + length:
            return
        status = int(head[9:12])
        del self.buffer[: end + 4 + length]
        started, self.started = self.started, None
        if started is not None:
            self.posts.done(status, *started)
        self.posts.ready(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
        if self in self.posts.free:
            self.posts.free.remove(self)
        if self in self.posts.links:
            self.posts.links.remove(self)
            if self.started is not None:
                self.posts.done(0, *self.started)
            self.posts.reopen(self)


class LogHistogram:
    """Counts of values in bins 0.5 % wide (geometric, from 10 us to ~17 min), so that a run of millions of
    latencies takes the same memory as one of thousands: percentiles to within half a percent."""

    LOW = 0.01
    RATIO = 1.005
    BINS = 3_700

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS, dtype=np.int64)
        self.n = 0

    def add(self, value: float) -> None:
        k = 0 if value <= self.LOW else int(math.log(value / self.LOW) / math.log(self.RATIO)) + 1
        self.counts[min(k, self.BINS - 1)] += 1
        self.n += 1

    def merge(self, counts: np.ndarray) -> None:
        self.counts += counts
        self.n += int(counts.sum())

    def percentile(self, q: float) -> float:
        """The value below which ``q`` % of the values lie (the upper edge of its bin); inf when empty."""
        if not self.n:
            return math.inf
        k = int(np.searchsorted(np.cumsum(self.counts), math.ceil(q / 100.0 * self.n)))
        return float(self.LOW * self.RATIO**k)


class PerSecondLatencies:
    """The median and the 99th percentile latency of the posts due in each second, kept as each second's posts
    are all answered (``SETTLE_S`` after it), so that only the seconds still open hold their latencies. A
    p99 made of a few seconds' spikes (a pause of the building or the front) shows apart from a broad tail."""

    SETTLE_S = 30

    def __init__(self) -> None:
        self._open: dict[int, list[float]] = {}
        self.done: dict[int, tuple[float, float]] = {}

    def add(self, second: int, latency_ms: float) -> None:
        self._open.setdefault(second, []).append(latency_ms)
        for settled in [s for s in self._open if s < second - self.SETTLE_S]:
            self._settle(settled)

    def _settle(self, second: int) -> None:
        p50, p99 = np.percentile(self._open.pop(second), [50, 99])
        self.done[second] = (float(p50), float(p99))

    def close(self) -> tuple[list[float], list[float]]:
        """The medians and the 99th percentiles, second by second."""
        for second in list(self._open):
            self._settle(second)
        ordered = [self.done[s] for s in sorted(self.done)]
        return [round(m, 1) for m, _ in ordered], [round(p, 1) for _, p in ordered]


@dataclass
class Results:
    latencies_ms: LogHistogram = field(default_factory=LogHistogram)
    per_second: PerSecondLatencies = field(default_factory=PerSecondLatencies)
    ws_lag_ms: LogHistogram = field(default_factory=LogHistogram)
    errors: int = 0
    sent: int = 0
    posted: int = 0
    """Every post, measured or not (the soak's batches)."""
    soak: list[dict[str, Any]] = field(default_factory=list)
    """The soak's samples (``Sampler``), one every ``--soak`` seconds."""
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


async def _dashboard(url: str, lags: LogHistogram, since_ms: float, stop: asyncio.Event) -> None:
    # an encounter re-publishes the peer's estimate with the peer's older time: count a user's time once, the
    # first time it is newer than any before, so the lag is from a batch's last step to the first position it
    # produced (a user's newest time, not every (user, time) seen: the dashboards' memory stays flat)
    newest: dict[str, int] = {}
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
                t_ms = int(t)
                if t_ms >= since_ms and t_ms > newest.get(user, -1):
                    newest[user] = t_ms
                    lags.add(received - t_ms)


def _dashboards(urls: list[str], n: int, since_ms: float, stop: Any, out: Any) -> None:
    """The dashboards, in a process of their own so that reading frames does not wait behind the phones'
    requests in one event loop (which read as live lag); sends back (lags, errors) when ``stop`` is set."""

    async def run() -> tuple[np.ndarray, list[str]]:
        lags = LogHistogram()
        done = asyncio.Event()
        tasks = [asyncio.create_task(_dashboard(urls[k % len(urls)], lags, since_ms, done)) for k in range(n)]
        while not stop.is_set():
            await asyncio.sleep(0.2)
        done.set()
        outcomes = await asyncio.gather(*tasks, return_exceptions=True)
        return lags.counts, [repr(o) for o in outcomes if isinstance(o, Exception)]

    out.send(asyncio.run(run()))


Sampler = Callable[[int], dict[str, Any]]
"""A soak's sample of the server (memory, disk), given the dashboards' process id."""


async def _drive(
    ports: list[int],
    keys: list[str],
    dashboard_keys: list[str],
    duration_s: float,
    n_dashboards: int,
    connections: int,
    meters: Meters,
    prefix: str = "",
    sampler: Sampler | None = None,
    sample_every_s: float = 60.0,
) -> Results:
    """The phones' connections are dealt round the ``ports`` (a cluster's fronts), the dashboards too."""
    n = len(keys)
    crowd = Crowd.create(n, seed=0)
    results = Results()
    buildings = len(dashboard_keys)
    lives = [
        f"ws://127.0.0.1:{ports[b % len(ports)]}/v1/buildings/{_building(b, buildings, prefix)}/live"
        f"?token={key}&batch=true"
        for b, key in enumerate(dashboard_keys)
    ]
    phase = np.linspace(0.0, 1.0, n, endpoint=False)
    building_of = np.arange(n) % buildings
    near: list[np.ndarray] = []
    joins = _join_second(n, duration_s)

    def bodies(phone: int, seq: int, now_ms: int) -> bytes:
        # a phone hears the phones near it in its own building only
        heard = near[phone][building_of[near[phone]] == building_of[phone]]
        return _body(crowd, phone, seq, now_ms, heard, _building(phone, buildings, prefix))

    # Every body formatted before the run when they fit in memory (the generator shares the cores with the
    # server): each timed at the moment it is due, from a start chosen past the time their formatting takes.
    seconds = math.ceil(duration_s)
    ready: list[dict[int, bytes]] | None = None
    start_epoch = time.time() + 0.5
    if n * seconds <= PREFORMAT_MAX:
        sample, probe = min(n, 200), copy.deepcopy(crowd)  # timed on a copy: the crowd's draws stay the run's
        began = time.perf_counter()
        for phone in range(sample):
            _body(probe, phone, 1, 0, np.zeros(0, dtype=int), "load")
        per_body = (time.perf_counter() - began) / sample
        start_epoch = time.time() + 1.0 + 2.0 * per_body * n * seconds + 0.05 * seconds
        ready = []
        for second in range(seconds):
            crowd.walk()
            near = crowd.neighbours()
            ready.append(
                {
                    phone: bodies(
                        phone, second - int(joins[phone]), int((start_epoch + second + phase[phone]) * 1000)
                    )
                    for phone in range(n)
                    if second >= joins[phone]
                }
            )
        if time.time() > start_epoch:
            print(f"load: bodies formatted {time.time() - start_epoch:.1f} s late", file=sys.stderr)
            start_epoch = time.time()
    context = multiprocessing.get_context("spawn")
    stop, (receive_lags, send_lags) = context.Event(), context.Pipe(duplex=False)
    since_ms = (max(start_epoch, time.time() + 0.5) + _warmup_s(duration_s)) * 1000.0
    dashboards = context.Process(target=_dashboards, args=(lives, n_dashboards, since_ms, stop, send_lags))
    dashboards.start()
    await asyncio.sleep(max(0.5, start_epoch - time.time()))

    warmup_s = _warmup_s(duration_s)

    async def sample_forever() -> None:
        assert sampler is not None
        while True:
            sample = await asyncio.to_thread(sampler, dashboards.pid or 0)
            results.soak.append(
                {"t_s": round(time.perf_counter() - start, 1), "batches": results.posted, **sample}
            )
            await asyncio.sleep(sample_every_s)

    def answered(status: int, due: float, measured: bool) -> None:
        if status != 200:
            results.errors += 1
        elif measured:
            latency = (time.perf_counter() - due) * 1000.0
            results.latencies_ms.add(latency)
            results.per_second.add(int(due - start), latency)
        outstanding[0] -= 1

    posts = Posts(ports, min(connections, n), answered)
    await posts.open()
    outstanding = [0]

    start = time.perf_counter()
    sampling = asyncio.create_task(sample_forever()) if sampler is not None else None
    second = 0
    while second < duration_s:
        if ready is None:
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
        due_order = np.argsort(phase)
        at = 0
        while at < due_order.size:  # every phone due by now posts at one wake-up, not a timer each
            delay = base + phase[due_order[at]] - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            now = time.perf_counter()
            while at < due_order.size and base + phase[due_order[at]] <= now:
                phone = int(due_order[at])
                at += 1
                seq = second - int(joins[phone])
                if seq < 0:  # not in the building yet
                    continue
                if ready is None:
                    body = bodies(phone, seq, int(time.time() * 1000))
                else:
                    body = ready[second].pop(phone)  # dropped once sent
                results.posted += 1
                outstanding[0] += 1
                path = f"/v1/buildings/{_building(phone, buildings, prefix)}/batches"
                posts.post(path, keys[phone], body, base + phase[phone], measure)
                results.sent += measure
        second += 1
    waited = time.perf_counter() + 30.0
    while outstanding[0] > 0 and time.perf_counter() < waited:
        await asyncio.sleep(0.01)
    if sampling is not None:
        sampling.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await sampling
    results.cpu_s = {part: meter() - cpu_at[0][part] for part, meter in meters.items()}
    results.generator_cpu_s = _cpu_seconds(os.getpid()) - cpu_at[1]
    results.measured_wall_s = time.perf_counter() - cpu_at[2]
    results.dashboards_cpu_s = _cpu_seconds(dashboards.pid or 0) - cpu_at[3]
    stop.set()
    lag_counts, results.dashboard_errors = receive_lags.recv()
    results.ws_lag_ms.merge(lag_counts)
    dashboards.join(timeout=30.0)
    posts.close()
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
    server_env: dict[str, str] | None = None,
    soak_every_s: float | None = None,
    soak_warmup_s: float = 300.0,
    keep_recordings: Path | None = None,
) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp, _database(Path(tmp), postgres) as database_url:
        data_dir = Path(tmp)
        keys, dashboards = _prepare(database_url, n, buildings)
        port = free_port()
        env = {
            **os.environ,
            "CROWDSLAM_DATA_DIR": str(data_dir),
            "CROWDSLAM_DATABASE_URL": database_url,
            **(server_env or {}),
        }
        server = serve_process(env, port, data_dir / "server.log", log_level="warning")
        pid = server.pid
        meters: Meters = {
            "server": lambda: _cpu_seconds(pid, children=True),
            "front": lambda: _cpu_seconds(pid),
        }
        if postgres is not None:
            meters["postgresql"] = _postgres_cpu_seconds
        engine = make_engine(database_url)
        sampler = None if soak_every_s is None else _soak_sampler(pid, data_dir, engine)
        try:
            started = time.perf_counter()
            results = asyncio.run(
                _drive(
                    [port],
                    keys,
                    dashboards,
                    duration_s,
                    n_dashboards,
                    connections,
                    meters,
                    sampler=sampler,
                    sample_every_s=soak_every_s or 60.0,
                )
            )
            elapsed = time.perf_counter() - started
            tables = None if soak_every_s is None else _table_sizes(engine)
        finally:
            server.terminate()
            server.wait(timeout=60)
            engine.dispose()
        if keep_recordings is not None and (data_dir / "recordings").is_dir():
            shutil.copytree(data_dir / "recordings", keep_recordings, dirs_exist_ok=True)
    row = _row(n, buildings, "sqlite" if postgres is None else "postgresql", duration_s, results, elapsed)
    cpu, wall = results.cpu_s, results.measured_wall_s
    row |= {
        "server_cpu_ms_per_batch": round(1e3 * cpu["server"] / max(results.sent, 1), 3),
        "server_cores": round(cpu["server"] / wall, 2),
        "front_cores": round(cpu["front"] / wall, 2),
        "building_cores": round((cpu["server"] - cpu["front"]) / wall, 2),
        # each process's CPU a batch: what a change to the front, the buildings or the generator costs
        "front_us_per_batch": round(1e6 * cpu["front"] / max(results.sent, 1), 1),
        "building_us_per_batch": round(1e6 * (cpu["server"] - cpu["front"]) / max(results.sent, 1), 1),
        "generator_us_per_batch": round(1e6 * results.generator_cpu_s / max(results.sent, 1), 1),
    }
    if "postgresql" in cpu:
        row["postgresql_cpu_ms_per_batch"] = round(1e3 * cpu["postgresql"] / max(results.sent, 1), 3)
        row["postgresql_cores"] = round(cpu["postgresql"] / wall, 2)
    if soak_every_s is not None:
        row["soak"] = soak_summary(results.soak, soak_warmup_s, soak_every_s, server_env or {})
        row["soak"]["tables_at_end"] = tables
    return row


def _rss_mb(pid: int) -> float:
    """Resident memory of a process (MB, 10^6 bytes): Linux /proc; NaN when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024 / 1e6
    except OSError:
        pass
    return math.nan


def _children(pid: int) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, IndexError):
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(stat.parent.name))
    return sorted(found)


def _child_label(pid: int) -> str:
    """A child of the server by what it runs: multiprocessing's resource tracker, or (spawned) a building's
    process."""
    try:
        command = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        command = ""
    kind = "resource tracker" if "resource_tracker" in command else "building process"
    return f"{kind} {pid}"


def _soak_sampler(server_pid: int, data_dir: Path, engine: Any) -> Sampler:
    """Every process's resident memory (the server's front and each of its children, this generator, the
    dashboards) and the disk the server takes: its data directory, its recordings, its database."""

    def sample(dashboards_pid: int) -> dict[str, Any]:
        return {
            "front_rss_mb": round(_rss_mb(server_pid), 1),
            "children_rss_mb": {_child_label(p): round(_rss_mb(p), 1) for p in _children(server_pid)},
            "generator_rss_mb": round(_rss_mb(os.getpid()), 1),
            "dashboards_rss_mb": round(_rss_mb(dashboards_pid), 1),
            "data_dir_mb": round(tree_bytes(data_dir) / 1e6, 2),
            "recordings_mb": round(tree_bytes(data_dir / "recordings") / 1e6, 2),
            "database_mb": round(database_bytes(engine) / 1e6, 2),
        }

    return sample


def _table_sizes(engine: Any) -> dict[str, dict[str, float]]:
    """Each table's rows and its bytes with its indexes (SQLite's ``dbstat``, PostgreSQL's
    ``pg_total_relation_size``), and the bytes a row: the disk budget's figures. On PostgreSQL also each
    table's dead rows and autovacuum runs."""
    from sqlalchemy import inspect, text

    out: dict[str, dict[str, float]] = {}
    with engine.connect() as connection:
        names = inspect(connection).get_table_names()
        if engine.dialect.name == "sqlite":
            pages = dict(connection.execute(text("SELECT name, SUM(pgsize) FROM dbstat GROUP BY name")).all())
            index_of = dict(connection.execute(text("SELECT name, tbl_name FROM sqlite_master")).all())
            sizes = dict.fromkeys(names, 0)
            for name, size in pages.items():
                table = index_of.get(name, name)
                if table in sizes:
                    sizes[table] += int(size)
            free = connection.execute(text("PRAGMA freelist_count")).scalar_one()
            page = connection.execute(text("PRAGMA page_size")).scalar_one()
            out["(free pages)"] = {"rows": 0, "mb": round(free * page / 1e6, 2), "bytes_per_row": 0.0}
        else:
            sizes = {
                n: int(connection.execute(text(f"SELECT pg_total_relation_size('{n}')")).scalar_one())
                for n in names
            }
            vacuums = {
                name: {"dead_rows": dead, "autovacuums": count}
                for name, dead, count in connection.execute(
                    text("SELECT relname, n_dead_tup, autovacuum_count FROM pg_stat_user_tables")
                )
            }
        for name in names:
            rows = int(connection.execute(text(f'SELECT COUNT(*) FROM "{name}"')).scalar_one())
            if rows or sizes[name] > 1e6:
                out[name] = {
                    "rows": rows,
                    "mb": round(sizes[name] / 1e6, 2),
                    "bytes_per_row": round(sizes[name] / max(rows, 1), 1),
                }
                if engine.dialect.name != "sqlite":
                    out[name] |= vacuums.get(name, {})  # autovacuum keeping up: few dead rows
    return out


def soak_summary(
    samples: list[dict[str, Any]], warmup_s: float, every_s: float, server_env: dict[str, str]
) -> dict[str, Any]:
    """The soak's samples and, after ``warmup_s``, each series' slope (a least-squares line, per minute)
    and the disk each batch costs (the series' growth over the batches posted meanwhile)."""
    after = [s for s in samples if s["t_s"] >= warmup_s]
    slopes: dict[str, Any] = {}
    per_batch: dict[str, float] = {}
    if len(after) >= 3:
        minutes = np.array([s["t_s"] for s in after]) / 60.0
        batches = np.array([s["batches"] for s in after], dtype=float)

        def slope(values: list[float]) -> float:
            return round(float(np.polyfit(minutes, np.array(values, dtype=float), 1)[0]), 3)

        for key in ("front_rss_mb", "generator_rss_mb", "dashboards_rss_mb", "data_dir_mb", "recordings_mb",
                    "database_mb"):  # fmt: skip
            slopes[key] = slope([s[key] for s in after])
        # a child's slope over the samples after the warm-up that all hold it (one restarted is two)
        children = set.intersection(*(set(s["children_rss_mb"]) for s in after))
        slopes["children_rss_mb"] = {
            child: slope([s["children_rss_mb"][child] for s in after]) for child in sorted(children)
        }
        batches_per_min = float(np.polyfit(minutes, batches, 1)[0])
        for key in ("data_dir_mb", "recordings_mb", "database_mb"):
            per_batch[key.replace("_mb", "")] = round(slopes[key] * 1e6 / max(batches_per_min, 1.0), 1)
    return {
        "every_s": every_s,
        "warmup_s": warmup_s,
        "server_env": server_env,
        "slopes_per_min_after_warmup": slopes,
        "bytes_per_batch_after_warmup": per_batch,
        "samples": samples,
    }


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
    lat, lag = results.latencies_ms, results.ws_lag_ms
    measured_s = duration_s - _warmup_s(duration_s)
    medians, p99s = results.per_second.close()
    return {
        "phones": n,
        "buildings": buildings,
        "database": database,
        "offered_per_s": n,
        "batches_per_s": round(lat.n / measured_s, 1),
        "p50_ms": round(lat.percentile(50), 1),
        "p99_ms": round(lat.percentile(99), 1),
        "ws_lag_p50_ms": round(lag.percentile(50), 1),
        "ws_lag_p99_ms": round(lag.percentile(99), 1),
        "p50_ms_per_second": medians,
        "p99_ms_per_second": p99s,
        "ws_positions": lag.n,
        "errors": results.errors + len(results.dashboard_errors),
        "generator_cores": round(results.generator_cpu_s / results.measured_wall_s, 2),
        "dashboards_cores": round(results.dashboards_cpu_s / results.measured_wall_s, 2),
        "dashboard_errors": results.dashboard_errors[:3],
        "seconds": round(elapsed, 1),
    }


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
    parser.add_argument(
        "--soak",
        type=float,
        metavar="SECONDS",
        help="a soak: sample every process's memory and the server's disk this often, and report their "
        "slopes after --soak-warmup (run it with a long --duration)",
    )
    parser.add_argument("--soak-warmup", type=float, default=300.0, metavar="SECONDS")
    parser.add_argument(
        "--server-env",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a setting of the server's (e.g. CROWDSLAM_POSITION_HISTORY_DAYS=0.01 to shorten a window)",
    )
    parser.add_argument("--plot", type=Path, help="with --soak: draw memory and disk over time here (PNG)")
    parser.add_argument(
        "--keep-recordings",
        type=Path,
        metavar="DIR",
        help="copy the server's recordings here at the end (e.g. to replay them: crowdslam replay --offline)",
    )
    parser.add_argument("--json", type=Path, help="also write the result here")
    args = parser.parse_args()
    server_env = dict(item.split("=", 1) for item in args.server_env)
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
            row = run_one(
                n,
                args.duration,
                args.dashboards,
                args.connections,
                args.buildings,
                args.postgres,
                server_env,
                args.soak,
                args.soak_warmup,
                args.keep_recordings,
            )
            if args.plot is not None and "soak" in row:
                plot_soak(row, args.plot.with_name(f"{args.plot.stem}-{n}{args.plot.suffix}"))
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


def plot_soak(row: dict[str, Any], path: Path) -> None:
    """Memory (every process) and disk (data directory, recordings, database) over the soak."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = row["soak"]["samples"]
    minutes = [s["t_s"] / 60.0 for s in samples]
    fig, (memory, disk) = plt.subplots(1, 2, figsize=(11, 4))
    for key, label in (("front_rss_mb", "front"), ("generator_rss_mb", "load generator"),
                       ("dashboards_rss_mb", "dashboards")):  # fmt: skip
        memory.plot(minutes, [s[key] for s in samples], label=label)
    for child in sorted({c for s in samples for c in s["children_rss_mb"]}):
        memory.plot(minutes, [s["children_rss_mb"].get(child, math.nan) for s in samples], label=child)
    for key, label in (("data_dir_mb", "data directory"), ("recordings_mb", "recordings"),
                       ("database_mb", "database")):  # fmt: skip
        disk.plot(minutes, [s[key] for s in samples], label=label)
    memory.set(xlabel="minutes", ylabel="resident memory (MB)", title=f"{row['phones']} phones")
    disk.set(xlabel="minutes", ylabel="MB", title=f"disk, {row['database']}")
    for axes in (memory, disk):
        axes.axvline(row["soak"]["warmup_s"] / 60.0, color="grey", linestyle=":")
        axes.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
