"""The warm-up compiles every kernel a building's batch path calls: after it, a simulated crowd run through a
building (in groups and one batch at a time, on the serial and the parallel kernels) compiles nothing new.
In a fresh interpreter, where only what the warm-up called is loaded; numba's on-disk cache makes both
parts cheap after the first run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]

SCRIPT = r"""
import importlib, json, pkgutil, sys, tempfile, time
from pathlib import Path

sys.path.insert(0, {root!r})
from numba.core.registry import CPUDispatcher

import slam_core
from server.slam.config import load_calibration, tracker_params
from server.slam.warmup import warm_kernels
from server.buildings.config import TrackingConfig
from server.buildings.submissions import Submission
from server.settings import Settings
from server.simulation.phones import simulated_batches
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade
from server.store.models import BuildingRow
from server.buildings.host import BuildingHost
from slam_core.filter.kernels.serial import PARALLEL_MIN_USERS
from slam_core.sim.simulation import simulate
from tests.server.recordings.test_recorder import small_crowd


def signatures():
    found = {{}}
    for module in pkgutil.walk_packages(slam_core.__path__, "slam_core."):
        for name, obj in vars(importlib.import_module(module.name)).items():
            if isinstance(obj, CPUDispatcher) and obj.__module__ == module.name:
                found[module.name + "." + name] = sorted(map(str, obj.signatures))
    return found


settings = Settings()
params, calibration = tracker_params(settings), load_calibration(settings.encounter_calibration)
warm_kernels(params, calibration)
warmed = signatures()
with tempfile.TemporaryDirectory() as tmp:
    engine = make_engine(f"sqlite:///{{Path(tmp) / 'db.sqlite3'}}")
    upgrade(engine)
    sessions = make_session_factory(engine)
    with sessions.begin() as session:
        session.add(BuildingRow(id="b", name="b", rotation_rad=0.0))
    building = BuildingHost("b", sessions, TrackingConfig(params, calibration))
    groups = {{}}
    for batch in simulated_batches(simulate(small_crowd(users=23, walk_m=150.0), 3), "b"):
        groups.setdefault((batch.time_span_ms() or (0, 0))[1], []).append(batch)
    for k, group in enumerate(groups.values()):
        building.tracker.filters.parallel_min_users = 1 if k % 2 else PARALLEL_MIN_USERS
        subs = [Submission.of(b, b.model_dump_json().encode(), time.time_ns()) for b in group]
        for part in (subs,) if k % 3 else ([s] for s in subs):
            building.process(list(part))
    engine.dispose()
after = signatures()
print(json.dumps({{"warmed": sum(map(len, warmed.values())),
                   "new": {{k: v for k, v in after.items() if set(v) - set(warmed.get(k, []))}}}}))
"""


def test_after_the_warm_up_a_crowd_compiles_no_kernel() -> None:
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(root=str(ROOT))],
        capture_output=True,
        text=True,
        env=dict(os.environ),  # the suite's NUMBA_CACHE_DIR (tests/conftest.py)
        check=False,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["warmed"] >= 10  # the oracle sees the warm-up's kernels at all
    assert result["new"] == {}, f"kernels the warm-up missed: {result['new']}"
