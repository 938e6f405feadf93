"""Regenerate the golden recording and its expected estimates (run only when a change is intended):

python tests/golden/regenerate.py                    # a new recording and its estimates
python tests/golden/regenerate.py --estimates-only   # the same recording, new expected estimates
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from server.slam.numba_cache import configure_numba_cache  # noqa: E402

configure_numba_cache()

from server.recordings.recorder import BuildingRecorder, read_batches  # noqa: E402
from server.replay import replay_offline  # noqa: E402
from server.settings import Settings  # noqa: E402
from server.simulation.phones import simulated_batches  # noqa: E402
from slam_core.sim.simulation import simulate  # noqa: E402
from tests.server.recordings.test_recorder import small_crowd  # noqa: E402


def main() -> None:
    target = HERE / "small-crowd.mcap"
    if "--estimates-only" not in sys.argv[1:]:
        record(target)
    report = replay_offline(read_batches(target), Settings(data_dir=HERE, seed=0))
    (HERE / "small-crowd.json").write_text(json.dumps(report.summary(), indent=1) + "\n")
    print(f"{report.batches} batches, {len(report.latest)} users")


def record(target: Path) -> None:
    sim = simulate(small_crowd(), 7)
    tmp = HERE / "tmp-recording"
    recorder = BuildingRecorder(tmp, "golden")
    t = time.time_ns()
    for k, batch in enumerate(simulated_batches(sim, "golden")):
        recorder.record_batch(batch.model_dump_json(exclude_none=True).encode(), t + k)
    recorder.close()
    (produced,) = (tmp / "golden").glob("*.mcap")
    produced.replace(target)
    (tmp / "golden").rmdir()
    tmp.rmdir()


if __name__ == "__main__":
    main()
