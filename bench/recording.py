"""Recording benchmark: what a batch costs the building's recording, in CPU and on disk.

    python bench/recording.py [--phones 1000] [--seconds 120] [--group 40] [--json OUT]

The load benchmark's crowd (``bench/load.py``: two steps a second, a WiFi scan every 2 s, Bluetooth
sightings of the phones within 8 m) posts for ``--seconds``; each batch and the estimate it produced are
written through ``BuildingRecorder`` as a building writes them, a group of ``--group`` batches at a time
(the batches, then their estimates, then the group's ``flush``). The bodies and estimates are made before
the clock starts: only the recorder's CPU is measured (this process's CPU time). Prints JSON: CPU
microseconds a batch, bytes a batch on disk, and what that is a day at 1,000 phones. It uses only the
recorder's interface that every version has, so the same script measures an older checkout with
``PYTHONPATH=that/checkout``.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # an older checkout on PYTHONPATH comes first
    sys.path.append(str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from load import Crowd, _body
from report import emit

from schemas.estimates import Estimate, EstimateSource
from server.recordings.recorder import BuildingRecorder

T0_MS = 1_800_000_000_000


def _inputs(phones: int, seconds: int) -> list[tuple[list[bytes], list[Estimate], int]]:
    """Each second's bodies and estimates (a filter's: the true position plus a metre of noise, a covariance
    of about a square metre), with the second's receive time in nanoseconds."""
    crowd = Crowd.create(phones, seed=0)
    rng = np.random.default_rng(1)
    out = []
    for second in range(seconds):
        crowd.walk()
        near = crowd.neighbours()
        now_ms = T0_MS + 1000 * second
        bodies = [_body(crowd, p, second, now_ms, near[p], "load") for p in range(phones)]
        noisy = crowd.xy + rng.normal(0.0, 1.0, crowd.xy.shape)
        spread = rng.uniform(0.3, 2.0, (phones, 2))
        estimates = [
            Estimate(
                building_id="load",
                user_id=f"load-{p:05d}",
                device_id=f"load-{p:05d}",
                t_ms=now_ms,
                position={"x_m": float(x), "y_m": float(y)},
                covariance_m2=[[float(a), 0.1 * math.sqrt(a * b)], [0.1 * math.sqrt(a * b), float(b)]],
                best_particle={"x_m": float(x) + 0.3, "y_m": float(y) - 0.2},
                heading_rad=float((math.pi / 2 - crowd.azimuth[p] + math.pi) % (2 * math.pi) - math.pi),
                source=EstimateSource.DYNAMICSLAM,
            )
            for p, ((x, y), (a, b)) in enumerate(zip(noisy.tolist(), spread.tolist(), strict=True))
        ]
        out.append((bodies, estimates, now_ms * 1_000_000))
    return out


def run(phones: int, seconds: int, group: int) -> dict[str, object]:
    inputs = _inputs(phones, seconds)
    with tempfile.TemporaryDirectory() as tmp:
        recorder = BuildingRecorder(Path(tmp), "load")
        started_cpu, started = time.process_time(), time.perf_counter()
        for bodies, estimates, received_ns in inputs:
            for first in range(0, len(bodies), group):
                for body in bodies[first : first + group]:
                    recorder.record_batch(body, received_ns)
                recorder.record_estimates(estimates[first : first + group], received_ns)
                if hasattr(
                    recorder, "flush"
                ):  # a group's end (versions that wrote record by record had none)
                    recorder.flush()
        recorder.close()
        cpu_s, wall_s = time.process_time() - started_cpu, time.perf_counter() - started
        size = sum(f.stat().st_size for f in Path(tmp).rglob("*.mcap"))
    batches = phones * seconds
    bytes_per_batch = size / batches
    return {
        "phones": phones,
        "seconds": seconds,
        "group": group,
        "batches": batches,
        "cpu_us_per_batch": round(1e6 * cpu_s / batches, 2),
        "wall_us_per_batch": round(1e6 * wall_s / batches, 2),
        "bytes_per_batch": round(bytes_per_batch, 1),
        "gb_a_day_at_1000_phones": round(bytes_per_batch * 86_400 * 1000 / 1e9, 2),
        "body_bytes_per_batch": round(sum(len(b) for bs, _, _ in inputs for b in bs) / batches, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--phones", type=int, default=1000)
    parser.add_argument("--seconds", type=int, default=120)
    parser.add_argument("--group", type=int, default=40, help="batches a building writes between flushes")
    parser.add_argument("--json", type=Path, help="also write the result here")
    args = parser.parse_args()
    emit({"recording": run(args.phones, args.seconds, args.group)}, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
