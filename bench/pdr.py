"""PDR front-end benchmark: how many times faster than real time one core dead-reckons real phone IMU.

    python bench/pdr.py [--floor crowdslam-data/datasets/msindoor20/site1/F1] [--json OUT]

Every walk of the floor goes through ``slam_core.sensing.pdr.online.pdr_steps`` in the one-second batches a
phone posts (state carried between batches), with the phone's rotation vector alone, with the rotation vector
and the gyroscope (the server's usual path: gyroscope heading referenced to north) and with the Madgwick
filter on gyroscope + magnetometer (phones without a rotation vector). Time is process CPU time
on one thread. Prints one JSON object: realtime_x per orientation source, per-batch microseconds, steps.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from server.slam.numba_cache import configure_numba_cache

configure_numba_cache()
from report import emit

from server.datasets.msindoor import read_floor, read_trace
from slam_core.sensing.pdr.online import ImuSamples, PdrParams, PdrState, pdr_steps


def _batches(trace_streams: dict[str, np.ndarray], sources: tuple[str, ...]) -> list[ImuSamples]:
    acc = trace_streams["accelerometer"]
    rv = trace_streams.get("rotation_vector", np.zeros((0, 4)))
    columns = {
        "gyr": trace_streams.get("gyroscope", np.zeros((0, 4))),
        "mag": trace_streams.get("magnetometer", np.zeros((0, 4))),
        "rv": np.column_stack([rv, np.full(len(rv), np.nan)]),
    }
    empty = {"gyr": np.zeros((0, 4)), "mag": np.zeros((0, 4)), "rv": np.zeros((0, 5))}
    out = []
    for start in np.arange(acc[0, 0], acc[-1, 0] + 1, 1000.0):

        def cut(rows: np.ndarray, start: float = start) -> np.ndarray:
            return rows[(rows[:, 0] >= start) & (rows[:, 0] < start + 1000.0)]

        out.append(ImuSamples(acc=cut(acc), **{**empty, **{k: cut(columns[k]) for k in sources}}))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--floor",
        type=Path,
        default=ROOT / "crowdslam-data/datasets/msindoor20/site1/F1",
        help="a floor of walks (crowdslam datasets fetch msindoor20 puts them there)",
    )
    parser.add_argument("--json", type=Path, metavar="OUT")
    args = parser.parse_args()
    walks = [read_trace(p).streams for p in read_floor(args.floor).traces]
    walks = [w for w in walks if len(w.get("accelerometer", ()))]
    seconds = sum((w["accelerometer"][-1, 0] - w["accelerometer"][0, 0]) / 1000.0 for w in walks)
    params = PdrParams()
    result: dict[str, object] = {
        "floor": str(args.floor),
        "walks": len(walks),
        "data_seconds": round(seconds, 1),
    }
    for label, sources in (
        ("rotation_vector", ("rv",)),
        ("rotation_vector_gyro", ("rv", "gyr")),
        ("madgwick_marg", ("gyr", "mag")),
    ):
        prepared = [_batches(w, sources) for w in walks]
        pdr_steps(PdrState(), prepared[0][0], params)  # compile / load the kernels outside the timing
        steps = 0
        started = time.process_time()
        for batches in prepared:
            state = PdrState()
            for batch in batches:
                steps += pdr_steps(state, batch, params).t_ms.size
        cpu = time.process_time() - started
        n_batches = sum(len(b) for b in prepared)
        result[label] = {
            "realtime_x": round(seconds / cpu, 1),
            "batch_us": round(1e6 * cpu / n_batches, 1),
            "batches": n_batches,
            "steps": steps,
        }
    emit(result, args.json)


if __name__ == "__main__":
    main()
