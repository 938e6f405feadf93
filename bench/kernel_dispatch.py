"""Parallel kernels against their serial twins, on an idle machine and with another process busy.

    python bench/kernel_dispatch.py [--users 8,32,128,512,2048] [--calls 300] [--json OUT]

The engine runs a kernel serially below ``slam_core.filter.kernels.serial.PARALLEL_MIN_USERS`` users per
call. This measures why: the summary (``summarise``) and the motion update (``motion_update``, two steps per
user) over n users, each call followed by a 2 ms pause (a building's kernels come between Python work, so
numba's thread pool has gone to sleep by the next call), once with the other cores idle and once with a
process spinning on one core (the HTTP front and the phones' sockets on a loaded server). Prints one JSON
object: per row ``kernel, users, other_core, parallel_mean_us, parallel_p99_us, serial_mean_us,
serial_p99_us``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from server.slam.numba_cache import configure_numba_cache

configure_numba_cache()

from report import emit

from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.filter.params import FilterParams


def _spin(stop: Any) -> None:
    while not stop.is_set():
        pass


def _times_us(call: Any, calls: int) -> np.ndarray:
    call()
    out = np.empty(calls)
    for k in range(calls):
        t0 = time.perf_counter()
        call()
        out[k] = (time.perf_counter() - t0) * 1e6
        time.sleep(0.002)
    return out


def _row(kernel: str, users: int, other: str, par: np.ndarray, ser: np.ndarray) -> dict[str, object]:
    return {
        "kernel": kernel,
        "users": users,
        "other_core": other,
        "parallel_mean_us": round(float(par.mean()), 1),
        "parallel_p99_us": round(float(np.percentile(par, 99)), 1),
        "serial_mean_us": round(float(ser.mean()), 1),
        "serial_p99_us": round(float(np.percentile(ser, 99)), 1),
    }


def run(sizes: list[int], calls: int) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    engines = {}
    for n in sizes:
        engine = DynamicSlam(FilterParams(), seed=0, initial_capacity=n)
        users = np.array([engine.add_user(float(i % 60), float(i // 60)) for i in range(n)])
        engines[n] = (engine, users)
    context = multiprocessing.get_context("spawn")
    for other in ("idle", "busy"):
        stop = context.Event()
        spinner = context.Process(target=_spin, args=(stop,), daemon=True) if other == "busy" else None
        if spinner is not None:
            spinner.start()
            time.sleep(0.5)
        try:
            for n in sizes:
                engine, users = engines[n]
                steps = (np.arange(0, 2 * n + 1, 2), np.full(2 * n, 0.7), np.full(2 * n, 0.3))
                for kernel, call in (
                    ("summarise", lambda e=engine, u=users: e.summaries(u)),
                    ("motion_update", lambda e=engine, u=users, s=steps: e.step(u, *s)),
                ):
                    engine.parallel_min_users = 1
                    par = _times_us(call, calls)
                    engine.parallel_min_users = n + 1
                    ser = _times_us(call, calls)
                    rows.append(_row(kernel, n, other, par, ser))
        finally:
            stop.set()
            if spinner is not None:
                spinner.join()
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--users", default="8,32,128,512,2048", help="users per call, comma-separated")
    parser.add_argument("--calls", type=int, default=300, help="timed calls per kernel, size and variant")
    parser.add_argument("--json", type=Path, help="also write the result here")
    args = parser.parse_args()
    try:
        sizes = [int(s) for s in args.users.split(",")]
    except ValueError:
        parser.error("--users takes comma-separated integers")
    if not sizes or min(sizes) < 1 or args.calls < 1:
        parser.error("--users and --calls must be at least 1")
    result = {"rows": run(sizes, args.calls)}
    emit(result, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
