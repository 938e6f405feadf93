"""The simulated testbed's phones through the server's tracker, as the demo posts them: every batch in time
order, one per tracker call (``server.simulated_phones``), converted as the API converts it.

``slam_core.evaluation`` steps every user together, tick by tick; here each phone's one-second batch is
applied on its own, so a reading between two users is often applied before the other's batch for that second
has arrived. This measures the live path, with the server's own tracker parameters (extended anchor types,
the shipped encounter calibration) in the chosen mode.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from server.convert import BuildingContext, anchor_type_index, to_user_batch
from server.datasets.msindoor_replay import ReplayOptions, replay_params
from server.simulated_phones import EPOCH_MS, known_anchors, simulated_batches
from slam_core.encounters import Calibration
from slam_core.metrics import error_summary
from slam_core.simulate import Scenario, simulate
from slam_core.tracker import BuildingTracker, TrackerParams


def replay_simulation(
    scenario: Scenario,
    options: ReplayOptions,
    base_params: TrackerParams,
    calibration: Calibration,
    progress: Callable[[int], None] | None = None,
) -> tuple[dict[str, Any], np.ndarray]:
    """Replay the scenario's crowd (seed ``options.seed``) through a tracker with the server's parameters
    (``base_params``, in the options' mode); returns the metrics and the error of every estimate (one per
    batch with steps, against the simulated truth at the estimate's time, in metres)."""
    started = time.perf_counter()
    sim = simulate(scenario, options.seed)
    tracker = BuildingTracker(replay_params(base_params, options), calibration, seed=options.seed)
    known: dict[str, tuple[float, float]] = {}
    for k, anchor in enumerate(known_anchors(sim)):
        tracker.pin_anchor(np.array(anchor.position), anchor_type_index(anchor.type))
        known[f"known-{k}"] = (float(anchor.position[0]), float(anchor.position[1]))
    ctx = BuildingContext("simulated", None, known)
    errors: list[float] = []
    applied = 0
    for batch in simulated_batches(sim, "simulated"):
        user_batch = to_user_batch(batch, ctx).user_batch
        outcome = tracker.apply([user_batch])
        applied += sum(e.applied for e in outcome.encounters)
        if progress is not None:
            progress(1)
        if not batch.steps or not tracker.is_tracking(user_batch.user):
            continue
        t_ms = tracker.last_time_ms(user_batch.user)
        if options.mode == "pdr":
            xy = tracker.dead_reckoning(user_batch.user)
        else:
            row = outcome.estimates[user_batch.user]
            xy, t_ms = np.array([row.x, row.y]), row.t_ms
        assert xy is not None
        user = int(batch.device_id.rsplit("-", 1)[-1])
        errors.append(float(np.linalg.norm(xy - sim.true_position(user, (t_ms - EPOCH_MS) / 1000.0))))
    error_array = np.array(errors)
    n_users = len(sim.users)
    result: dict[str, Any] = {
        "mode": options.mode,
        "seed": options.seed,
        "path": "tracker",
        **error_summary(error_array),
        "n_estimates": int(error_array.size),
        "encounters_applied_per_user": 2 * applied / n_users,
        "seconds": time.perf_counter() - started,
    }
    return result, error_array
