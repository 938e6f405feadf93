"""Compile (or load from numba's on-disk cache) every kernel the batch path uses, before the first request.

A kernel first called by a request is compiled while that request and every one queued behind it waits
(tens of seconds for all of them on a cold cache). The warm-up therefore runs the tracker through
what a busy building does: single phones and groups, each on the serial twins and on the parallel kernels
(``slam_core.filter.kernels.serial``), and a small crowd long enough that its WiFi scans meet (Eq. 3), its
Bluetooth sightings pair up, its scans outgrow the encounter index and the fingerprint map (both
compact), and the fingerprint map places scans. A kernel missed here was seen only by a load run from a
fresh install: ``tests/server/slam/test_warmup.py`` runs a simulated crowd through a building after the
warm-up and fails if any kernel still compiles.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import multiprocessing
import os
import queue
import time
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.queues import Queue
from pathlib import Path

import numba
import numpy as np

from server.process_lifetime import die_with, interrupts_held
from server.settings import Settings
from server.slam.config import load_calibration, tracker_params
from slam_core.encounters.models import Calibration
from slam_core.filter.kernels.serial import PARALLEL_MIN_USERS
from slam_core.sensing.pdr.online import ImuSamples, PdrState, pdr_steps
from slam_core.tracking.tracker import BuildingTracker, TrackerParams, UserBatch

CROWD_USERS = 12
CROWD_SECONDS = 100
"""Long enough for the crowd's ~1,200 scans to outgrow the encounter index's first 1,024 slots (it then
compacts) and to refill the fingerprint map's cells (it then compacts too)."""
ACCESS_POINTS = 24
SCAN_APS = 8

logger = logging.getLogger(__name__)


WARM_STEPS = 2 + CROWD_SECONDS + 1
"""What ``warm_kernels`` reports its progress in: the two pairs, each second of the crowd, the PDR."""

Progress = Callable[[int, int], None]
"""Called with (steps done, steps in all) as the warm-up goes."""


def warm_kernels(params: TrackerParams, calibration: Calibration, progress: Progress | None = None) -> None:
    report = progress or (lambda done, total: None)
    report(0, WARM_STEPS)
    for k, parallel_min_users in enumerate((1, PARALLEL_MIN_USERS)):
        _warm_pair(params, calibration, parallel_min_users)
        report(k + 1, WARM_STEPS)
    _warm_crowd(params, calibration, lambda second: report(3 + second, WARM_STEPS))

    t = np.arange(3_000.0, 4_000.0, 20.0)
    gravity = np.column_stack([t, np.zeros(t.size), np.zeros(t.size), np.full(t.size, 9.81)])
    pdr_steps(PdrState(), ImuSamples(acc=gravity, gyr=gravity * [1, 0, 0, 0], mag=gravity), params.pdr)
    report(WARM_STEPS, WARM_STEPS)


def _warm_pair(params: TrackerParams, calibration: Calibration, parallel_min_users: int) -> None:
    """Two users with a fix, steps, an anchor detection, an encounter and a position fix."""
    tracker = BuildingTracker(params, calibration, seed=0)
    tracker.filters.parallel_min_users = parallel_min_users
    tracker.pin_anchor(np.array([1.0, 0.0]), 0)
    for name in ("a", "b"):
        tracker.apply(
            [
                UserBatch(
                    user=name,
                    fix_t=np.array([1_000], dtype=np.int64),
                    fix_xy=np.zeros((1, 2)),
                    fix_sigma=np.array([0.5]),
                    fix_azimuth=np.array([np.pi / 2]),
                    step_t=np.array([1_500, 2_000], dtype=np.int64),
                    step_length=np.array([0.5, 0.5]),
                    step_azimuth=np.array([np.pi / 2, np.nan]),
                    step_turn=np.array([np.nan, 0.0]),
                    detect_t=np.array([2_000], dtype=np.int64),
                    detect_type=np.array([0], dtype=np.int64),
                )
            ]
        )
    tracker.filters.observe_encounters(np.array([0]), np.array([1]), np.array([1.0]), np.array([1.0]))
    tracker.filters.observe_position(np.array([0]), np.array([[1.0, 0.0]]), np.array([0.5]))


def _warm_crowd(params: TrackerParams, calibration: Calibration, seconds_done: Callable[[int], None]) -> None:
    """``CROWD_USERS`` phones walking round a 24 m square, one batch a second each (two steps, a WiFi scan,
    the Bluetooth sightings of the phones within 8 m), all of a second's batches in one call; calls
    alternate between the serial twins and the parallel kernels. The fingerprint map takes every scan
    (no cell refresh) and places one once it holds a few: the same kernels as a busy floor's, sooner."""
    fingerprints = replace(params.fingerprints, min_references=2 * params.fingerprints.k, cell_refresh_ms=0)
    tracker = BuildingTracker(replace(params, fingerprints=fingerprints), calibration, seed=0)
    rng = np.random.default_rng(0)
    ap_xy = rng.uniform(-4.0, 28.0, (ACCESS_POINTS, 2))
    bssids = [f"02:00:00:00:{k // 256:02x}:{k % 256:02x}" for k in range(ACCESS_POINTS)]
    perimeter = 4 * 24.0
    start = rng.uniform(0.0, perimeter, CROWD_USERS)
    t0 = 1_000_000
    for second in range(CROWD_SECONDS):
        t_ms = t0 + 1_000 * second
        walked = start + 1.4 * second
        xy = np.array([_on_square(s) for s in walked])
        heading = np.array([_heading_on_square(s) for s in walked])
        batches = []
        for u in range(CROWD_USERS):
            name = f"warm-{u}"
            first = second == 0
            d = np.hypot(*(ap_xy - xy[u]).T)
            rss = -40.0 - 25.0 * np.log10(np.maximum(d, 1.0)) + rng.normal(0.0, 3.0, ACCESS_POINTS)
            heard = np.argsort(-rss)[:SCAN_APS]
            near = [v for v in range(CROWD_USERS) if v != u and np.hypot(*(xy[v] - xy[u])) < 8.0]
            batches.append(
                UserBatch(
                    user=name,
                    ble_id=f"ble-{u}",
                    fix_t=np.array([t_ms - 500] if first else [], dtype=np.int64),
                    fix_xy=xy[u : u + 1] if first else np.zeros((0, 2)),
                    fix_sigma=np.array([1.0] if first else []),
                    fix_azimuth=np.array([heading[u]] if first else []),
                    step_t=np.array([t_ms - 500, t_ms], dtype=np.int64),
                    step_length=np.array([0.7, 0.7]),
                    step_azimuth=np.full(2, heading[u]),
                    step_turn=np.full(2, np.nan),
                    scan_t=np.array([t_ms], dtype=np.int64),
                    scan_offsets=np.array([0, SCAN_APS], dtype=np.int64),
                    scan_bssid=tuple(bssids[k] for k in heard),
                    scan_rss=np.round(rss[heard]),
                    scan_last_seen=np.full(SCAN_APS, t_ms, dtype=np.int64),
                    peer_t=np.full(len(near), t_ms, dtype=np.int64),
                    peer_id=tuple(f"ble-{v}" for v in near),
                    peer_rss=np.array([-60.0 - 2.0 * np.hypot(*(xy[v] - xy[u])) for v in near]),
                )
            )
        tracker.filters.parallel_min_users = 1 if second % 2 else PARALLEL_MIN_USERS
        tracker.apply(batches)
        seconds_done(second)


def _on_square(s: float) -> tuple[float, float]:
    """The point ``s`` metres anticlockwise round the 24 m square from its south-west corner."""
    side, along = divmod(s % 96.0, 24.0)
    return [(along, 0.0), (24.0, along), (24.0 - along, 24.0), (0.0, 24.0 - along)][int(side)]


def _heading_on_square(s: float) -> float:
    """Azimuth (clockwise from north) of the walk at ``s``: east, north, west, south."""
    return [np.pi / 2, 0.0, -np.pi / 2, np.pi][int((s % 96.0) // 24.0)]


def warm_kernels_for(
    settings: Settings, steps: Queue[int] | None = None, parent_pid: int | None = None
) -> None:
    """``warm_kernels`` with the tracker the settings configure; each step done is put on ``steps``. In a
    child started by process ``parent_pid``, it dies with that process (a server stopped while it compiles
    leaves no compile running)."""
    if parent_pid is not None:
        die_with(parent_pid)
    warm_kernels(
        tracker_params(settings),
        load_calibration(settings.encounter_calibration),
        None if steps is None else lambda done, total: steps.put(done),
    )


async def compile_kernels_in_child(settings: Settings, progress: Progress | None = None) -> None:
    """For buildings in processes of their own: compile every kernel once into numba's on-disk cache, in a
    short-lived child, before the server takes requests. Each building's process warms its kernels when
    it starts, at its building's first request: from the cache that takes a second or two, where a cold
    compile would hold the building's first batches and be repeated by every building starting with it. A
    child rather than the front itself, so that the front does not keep compiled code it never runs. Its
    progress is awaited on the event loop, not in a thread: a server stopped meanwhile (Ctrl-C) exits at
    once, and the child with it, where a thread waiting for it had held the exit until the compile ended."""
    started = time.perf_counter()
    warm = warm_marker()
    if warm is not None and warm.exists():  # every kernel is in the cache for this CPU already
        if progress is not None:
            progress(WARM_STEPS, WARM_STEPS)
        logger.info("kernels found in the cache (%s)", warm)
        return
    context = multiprocessing.get_context("spawn")
    steps: Queue[int] = context.Queue()
    process = context.Process(  # daemonic: a server exiting ends it rather than waiting for it
        target=warm_kernels_for,
        args=(settings, steps, os.getpid()),
        name="crowdslam-compile-kernels",
        daemon=True,
    )
    with interrupts_held():  # a terminal's Ctrl-C is the server's to handle, not the compile's
        process.start()
    try:
        while process.is_alive() or not steps.empty():
            try:
                done = steps.get_nowait()
            except queue.Empty:
                await asyncio.sleep(0.1)
                continue
            if progress is not None:
                progress(done, WARM_STEPS)
    finally:
        if process.is_alive():  # the server stopped first
            process.kill()
        process.join()
        steps.close()
    if process.exitcode != 0:
        raise RuntimeError(f"compiling the kernels failed in their process (exit code {process.exitcode})")
    if warm is not None:
        warm.touch()
    logger.info("kernels compiled into the cache in %.1f s", time.perf_counter() - started)


def warm_marker() -> Path | None:
    """The file that says numba's cache folder (``NUMBA_CACHE_DIR``, keyed by the kernels' sources) holds
    every kernel compiled for this machine's CPU: written once a compile child has run the whole warm-up, so
    that later starts spend no child on it (~2 s a start). None without a cache folder."""
    folder = os.environ.get("NUMBA_CACHE_DIR")
    if not folder:
        return None
    import llvmlite.binding as llvm  # loaded with numba already: the kernels' modules import it

    cpu = f"{llvm.get_host_cpu_name()} {llvm.get_host_cpu_features().flatten()} {numba.__version__}"
    return Path(folder) / f"warm-{hashlib.sha256(cpu.encode()).hexdigest()[:16]}"
