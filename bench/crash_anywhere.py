"""Crash anywhere, at more kill points than the test suite runs: the crash scenario (``tests/server/crash``:
three floors without a floor 0, a crowd of five and its operators at work) run once without a crash, then
once per seed with ``--kills`` SIGKILLs at seeded points, each compared with the first.

    python bench/crash_anywhere.py [--kills 20] [--seeds 0,1,2] [--store sqlite|postgresql]
                                   [--targets building,server | --cluster] [--json OUT]

``--store postgresql`` runs on a new database of the local PostgreSQL (``CROWDSLAM_TEST_POSTGRES_URL``, by
default ``postgresql+psycopg://postgres@127.0.0.1:5432/test``); ``--cluster`` kills the worker holding the
building in a cluster of one front and two workers (PostgreSQL and a private ``nats-server``). Prints JSON:
per seed, every kill (its step, target, how far into the request, what the first attempt was answered),
the batches checked ``duplicate`` afterwards, the seconds, and the differences from the run without a crash
(none is the only passing figure). Exits 1 if any run differs.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from server.slam.numba_cache import configure_numba_cache

configure_numba_cache()

from report import emit
from tqdm import tqdm

from server.cli.local_cluster import postgres_database
from tests.conftest import POSTGRES_ADMIN_URL
from tests.server.cluster.cluster import local_cluster
from tests.server.crash.harness import InCluster, Run, Target, differences, embedded, kill_points, play
from tests.server.crash.scenario import crash_scenario


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=20, help="kill points a run (default 20)")
    parser.add_argument("--seeds", default="0,1,2", help="one run a seed (default 0,1,2)")
    parser.add_argument("--store", choices=("sqlite", "postgresql"), default="sqlite")
    parser.add_argument("--targets", default="building,server", help="what a kill may take")
    parser.add_argument("--cluster", action="store_true", help="kill the worker holding the building")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    targets: tuple[Target, ...] = ("worker",) if args.cluster else tuple(args.targets.split(","))  # type: ignore[assignment]
    store = "postgresql" if args.cluster else args.store
    scenario = crash_scenario()
    if args.kills > len(scenario.killable):
        parser.error(f"--kills: the scenario has {len(scenario.killable)} steps a kill may fall in")
    work = Path(tempfile.mkdtemp(prefix="crowdslam-crash-"))
    try:
        started = time.monotonic()
        with embedded(work / "reference") as server:
            reference = play(scenario, server, [])
        reference_s = time.monotonic() - started
        runs: list[dict[str, Any]] = []
        failed = False
        for seed in tqdm(seeds, desc="crash runs", unit="run"):
            kills = kill_points(scenario, args.kills, seed, targets)
            root = work / f"seed-{seed}"
            root.mkdir()
            crashed = _run(scenario, kills, root, store, args.cluster)
            found = differences(reference, crashed)
            failed = failed or bool(found)
            runs.append(
                {
                    "seed": seed,
                    "kills": crashed.kills,
                    "duplicates_checked": crashed.duplicates_checked,
                    "seconds": round(crashed.seconds, 1),
                    "seconds_per_kill": round((crashed.seconds - reference.seconds) / max(1, args.kills), 2),
                    "differences": found,
                }
            )
        emit(
            {
                "benchmark": "crash_anywhere",
                "store": store,
                "cluster": args.cluster,
                "targets": list(targets),
                "steps": len(scenario.steps),
                "batches": len(reference.receipts),
                "kills_per_run": args.kills,
                "kill_points": args.kills * len(seeds),
                "runs_differing": sum(1 for r in runs if r["differences"]),
                "reference_seconds": round(reference_s, 1),
                "runs": runs,
            },
            args.json,
        )
        return 1 if failed else 0
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _run(scenario: Any, kills: list[Any], root: Path, store: str, cluster: bool) -> Run:
    if cluster:
        with local_cluster(root, fronts=1, workers=2) as running:
            return play(scenario, InCluster(running), kills)
    if store == "sqlite":
        with embedded(root) as server:
            return play(scenario, server, kills)
    with (
        postgres_database(POSTGRES_ADMIN_URL, prefix="crowdslam_crash") as url,
        embedded(root, url) as server,
    ):
        return play(scenario, server, kills)


if __name__ == "__main__":
    sys.exit(main())
