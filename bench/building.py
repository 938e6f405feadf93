"""Building benchmark: one building's batch path without HTTP, the part of the server that holds one core.

    python bench/building.py [--phones 1000] [--seconds 20] [--group 32] [--path process|thread|both]
                             [--zones N] [--postgres URL] [--json OUT] [--profile OUT.prof]

A building's tracking as its own process builds it (``server.buildings.host.open_building``: SQLite,
its write-ahead log checkpointed by a thread beside the batch path, recording on: the server's defaults; with
``--postgres``, a new database on that PostgreSQL server, as a cluster's worker holds it) is
fed the load benchmark's phones (``bench/load.py``: a batch per phone per second, two steps, a WiFi scan every
2 s, Bluetooth sightings) in groups of ``--group`` batches, the way the building's worker drains its queue
under load. Every phone posts its fix first; the figures count the seconds after that. Prints one JSON object:
``us_per_batch`` (wall time of ``process`` and of the JSON of its receipts and live messages, mean over the
seconds; ``_min``: the cheapest second; ``cpu_us_per_batch``: the process' CPU time over the same spans,
which a shared machine's stolen time inflates less), ``json_us_per_batch`` (that JSON alone), and what it
ran on. ``--path`` says which side of the front the batches arrive by: ``process`` (a building in its own
process, ``CROWDSLAM_BUILDING_PROCESSES``: the front has validated, converted and packed each batch, and the
building's time starts at unpickling it) or ``thread`` (a building in the server's process: it decodes and
converts each batch itself; numba's kernels on every core, where a building process runs them on one thread
as the server does); ``both`` alternates the two group by group and reports each (``us_per_batch_process``,
``_thread`` and their ratio): on a shared machine whose speed drifts, only runs interleaved like this
compare. Without the HTTP front, the load generator and the dashboards on the same cores, this is steadier
than ``bench/load.py`` and says what a change to the batch path costs.

With ``--zones N`` the building has N zones drawn over the phones' floor (a grid of rectangles, each a
twentieth of the floor's width, some with a dwell time) before the first batch: what the zone stage, the
visits and their events cost a batch (``bench/against.py . --here-args "--zones 100" -- bench/building.py
...`` compares it with none, alternately).

It also reports the pauses that hold a group, and so every batch queued behind it, with the building at
the end of the run: ``group_ms_p99`` and ``group_ms_max`` (per call of ``process``), ``snapshot_pickle_ms``
(the state pickled in the building's thread when a periodic snapshot is taken) and ``full_gc_ms`` (one
full pass of the cyclic collector, tuned as in the server: start-up objects frozen after the first second).

The kernels are warmed before the first batch, as a building's process warms them
(``server.slam.warmup.warm_kernels_for``), so that the first second, in which every phone posts its fix and
is admitted, measures what a new user's first batch costs and not the kernels' loading:
``admit_us_per_phone`` (wall time), ``admit_cpu_us_per_phone`` (CPU) and ``admit_vs_walking`` (that CPU over
``cpu_us_per_batch``).
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import gc
import math
import pickle
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from server.slam.numba_cache import configure_numba_cache

configure_numba_cache()

import numba
from load import FLOOR_M, Crowd, _body
from report import emit

from schemas.live import LIVE_MESSAGE_ADAPTER
from schemas.zones import ZoneIn, ZonePolygon
from server.buildings import snapshot as tracker_snapshot
from server.buildings.host import open_building
from server.buildings.submissions import Submission, batch_fields, received_batch
from server.cli.local_cluster import postgres_database
from server.errors import ProblemError
from server.gc_tuning import tune_gc_for_serving
from server.ingestion.decoding import decode_batch
from server.settings import Settings
from server.slam.warmup import warm_kernels_for
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade
from server.store.models import BuildingRow

THREADS = numba.get_num_threads()
"""numba's threads in the server's own process; a building process runs its kernels on one
(``server.buildings.process.serve_building``), and so does this benchmark on the ``process`` path."""


def run(
    phones: int,
    seconds: int,
    group: int,
    path: str,
    profile: Path | None,
    postgres: str | None,
    zones: int = 0,
) -> dict[str, object]:
    with contextlib.ExitStack() as stack:
        tmp = stack.enter_context(tempfile.TemporaryDirectory())
        url = (
            stack.enter_context(postgres_database(postgres, "bench_building"))
            if postgres
            else f"sqlite:///{Path(tmp) / 'crowdslam.sqlite3'}"
        )
        settings = Settings(data_dir=Path(tmp), database_url=url)
        engine = make_engine(settings.resolved_database_url)
        upgrade(engine)
        with make_session_factory(engine).begin() as s:
            s.add(BuildingRow(id="load", name="Load test", rotation_rad=0.0))
        numba.set_num_threads(1)
        warm_kernels_for(settings)  # as a building's process does before its first batch
        tune_gc_for_serving()  # and then the garbage collector, before the first batch too
        # the tracking a building's process serves with: its own engine with the write-ahead log
        # checkpointed by a thread beside the batch path, recording, snapshots and retention as configured
        building = open_building(settings, "load", engine)
        for k, body in enumerate(_zones(zones)):
            building.zones.put(f"zone-{k}", body)
        crowd = Crowd.create(phones, seed=0)
        start_ms = int(time.time() * 1000)
        per_second: list[float] = []
        cpu_per_second: list[float] = []
        json_per_second: list[float] = []
        group_ms: list[float] = []
        by_path = {"process": [0.0, 0], "thread": [0.0, 0]}  # seconds, batches
        profiler = cProfile.Profile() if profile is not None else None
        for second in range(seconds + 1):
            crowd.walk()
            near = crowd.neighbours()
            now_ms = start_ms + 1000 * second
            bodies = [
                _body(crowd, p, second, now_ms + p * 1000 // phones, near[p], "load") for p in range(phones)
            ]
            busy = json_busy = cpu = 0.0
            for first in range(0, phones, group):
                raws = bodies[first : first + group]
                use = path if path != "both" else ("process", "thread")[(first // group + second) % 2]
                numba.set_num_threads(1 if use == "process" else THREADS)  # as each kind of building runs
                frames = [_front(r) for r in raws] if use == "process" else []
                started, cpu_started = time.perf_counter(), time.process_time()
                if profiler is not None and second:
                    profiler.enable()
                if use == "process":
                    subs = [_building_side(f) for f in frames]
                else:
                    subs = [Submission.of(decode_batch(r, len(r)), r, time.time_ns()) for r in raws]
                result = building.process(subs)
                encoded = time.perf_counter()
                for receipt in result.receipts:
                    if isinstance(receipt, ProblemError):
                        raise RuntimeError(f"a batch failed: {receipt}")
                    receipt.model_dump_json()
                for message in result.messages:
                    LIVE_MESSAGE_ADAPTER.dump_json(message)
                if profiler is not None:
                    profiler.disable()
                done = time.perf_counter()
                busy += done - started
                cpu += time.process_time() - cpu_started
                json_busy += done - encoded
                if second:
                    group_ms.append((done - started) * 1e3)
                    by_path[use][0] += done - started
                    by_path[use][1] += len(raws)
            if second:  # the first second admits every phone (its fix): reported apart
                per_second.append(busy / phones * 1e6)
                cpu_per_second.append(cpu / phones * 1e6)
                json_per_second.append(json_busy / phones * 1e6)
            else:
                admit_us = busy / phones * 1e6
                admit_cpu_us = cpu / phones * 1e6
        if profiler is not None and profile is not None:
            profiler.dump_stats(profile)
        pickle_s = min(_timed(lambda: tracker_snapshot.pickled(building.building.state())) for _ in range(3))
        gc_s = min(_timed(gc.collect) for _ in range(3))
        building.close()
        assert building.recorder is not None
        building.recorder.close()
        engine.dispose()  # and its checkpoint thread
    paths = {}
    if path == "both":
        us = {p: by_path[p][0] / by_path[p][1] * 1e6 for p in by_path}
        paths = {f"us_per_batch_{p}": round(v, 1) for p, v in us.items()}
        paths["process_over_thread"] = round(us["process"] / us["thread"], 3)
    return {
        "phones": phones,
        "group": group,
        "path": path,
        "seconds": seconds,
        **paths,
        "us_per_batch": round(statistics.mean(per_second), 1),
        "us_per_batch_min": round(min(per_second), 1),
        "cpu_us_per_batch": round(statistics.mean(cpu_per_second), 1),
        "admit_us_per_phone": round(admit_us, 1),
        "admit_cpu_us_per_phone": round(admit_cpu_us, 1),
        "admit_vs_walking": round(admit_cpu_us / statistics.mean(cpu_per_second), 2),
        "json_us_per_batch": round(statistics.mean(json_per_second), 1),
        "batches_per_s_one_core": round(1e6 / statistics.mean(per_second)),
        "group_ms_p99": round(float(np.percentile(group_ms, 99)), 1),
        "group_ms_max": round(max(group_ms), 1),
        "snapshot_pickle_ms": round(pickle_s * 1e3, 1),
        "full_gc_ms": round(gc_s * 1e3, 1),
        "zones": zones,
        "zone_events": building.counters.zone_events,
        "fingerprint_fixes": building.counters.fingerprint_fixes,
        "encounters": building.counters.encounters,
        "database": "postgresql" if postgres else "sqlite",
    }


def _zones(n: int) -> list[ZoneIn]:
    """``n`` zones in a grid over the load's floor: rectangles a twentieth of its width across, every third
    with a dwell of a minute."""
    columns = max(1, math.ceil(math.sqrt(n)))
    rows = max(1, math.ceil(n / columns))
    width, height = FLOOR_M[0] / columns, FLOOR_M[1] / rows
    side_x, side_y = FLOOR_M[0] / 20, FLOOR_M[1] / 20
    out = []
    for k in range(n):
        x0, y0 = (k % columns) * width, (k // columns) * height
        ring = [(x0, y0), (x0 + side_x, y0), (x0 + side_x, y0 + side_y), (x0, y0 + side_y), (x0, y0)]
        out.append(
            ZoneIn(
                floor=0,
                name=f"zone {k}",
                polygon=ZonePolygon(type="Polygon", coordinates=[ring]),
                dwell_s=60.0 if k % 3 == 0 else None,
            )
        )
    return out


def _front(raw: bytes) -> bytes:
    """What the front of a building process sends for a batch (``BuildingProcess.submit``)."""
    submission = Submission.of(decode_batch(raw, len(raw)), raw, time.time_ns())
    return pickle.dumps(batch_fields(submission), protocol=pickle.HIGHEST_PROTOCOL)


def _building_side(frame: bytes) -> Submission:
    """The building process' side of ``_front`` (``building_process._BuildingLoop._flush``)."""
    return received_batch(*pickle.loads(frame))


def _timed(work: Callable[[], object]) -> float:
    started = time.perf_counter()
    work()
    return time.perf_counter() - started


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--phones", type=int, default=1000)
    parser.add_argument(
        "--seconds", type=int, default=20, help="measured seconds of batches (after the fixes)"
    )
    parser.add_argument("--group", type=int, default=32, help="batches per call of BuildingHost.process")
    parser.add_argument(
        "--path",
        choices=("process", "thread", "both"),
        default="process",
        help="batches converted by the front of a building process, or by the building itself",
    )
    parser.add_argument(
        "--postgres", metavar="URL", help="a PostgreSQL server whose databases may be created and dropped"
    )
    parser.add_argument("--zones", type=int, default=0, help="zones drawn over the floor first")
    parser.add_argument("--json", type=Path, help="also write the result here")
    parser.add_argument("--profile", type=Path, help="write a cProfile of the measured seconds here")
    args = parser.parse_args()
    if args.phones < 1 or args.seconds < 1 or args.group < 1:
        parser.error("--phones, --seconds and --group must be at least 1")
    if args.zones < 0:
        parser.error("--zones must not be negative")
    result = run(args.phones, args.seconds, args.group, args.path, args.profile, args.postgres, args.zones)
    emit(result, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
