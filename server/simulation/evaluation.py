"""``crowdslam evaluate --scenario``: a simulated crowd through the server's own tracker, scored against the
simulated truth.

The scenario's phones post their one-second batches in time order (``server.simulation.phones``), each
converted as the API converts it (``server.ingestion.convert``) and applied with ``BuildingTracker.apply``,
one batch per call, as the demo's phones reach a building: a reading between two users is often applied
before the other's batch for that second has arrived. What is measured here is the program the server runs,
with its tracker parameters (extended anchor types, the shipped encounter calibration) in the chosen mode.

Every batch with steps yields one scored estimate: the tracker's estimate at its time (``pdr``: the plain
dead reckoning) against the simulated truth at that time. The run is seeded by ``ReplayOptions.seed``: the
world and its phones from ``seed``, the filters from ``filter_seed`` (the same unless set), so that a figure
is reproduced by its command and the filters' own noise can be measured apart from the world's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from server.ingestion.convert import anchor_type_index, building_context, to_user_batch
from server.simulation.liars import liar_devices, lying
from server.simulation.phones import EPOCH_MS, device_id, known_anchors, simulated_batches
from server.slam.config import ReplayOptions, replay_params
from slam_core.encounters.models import Calibration
from slam_core.sim.encounters import meetings_per_user
from slam_core.sim.map_quality import map_quality
from slam_core.sim.simulation import Scenario, Simulation, room_zones, simulate
from slam_core.sim.statistics import error_summary
from slam_core.tracking.tracker import BuildingTracker, TrackerOutcome, TrackerParams
from slam_core.zones.visits import ZoneTally


def evaluate_scenario(
    scenario: Scenario,
    options: ReplayOptions,
    base_params: TrackerParams,
    calibration: Calibration,
    progress: Callable[[int], None] | None = None,
) -> tuple[dict[str, Any], np.ndarray]:
    """Replay the scenario's crowd (world seed ``options.seed``) through a tracker with the server's
    parameters (``base_params``, in the options' mode); returns the metrics and the error of every scored
    estimate (metres)."""
    started = time.perf_counter()
    sim = simulate(scenario, options.seed)
    params = replay_params(base_params, options)
    tracker = BuildingTracker(params, calibration, seed=options.tracker_seed)
    levels = tuple(range(sim.world.levels))
    if len(levels) > 1:  # as an operator creates the building: its floors, not their heights
        tracker.set_levels(levels)
    known: dict[str, int] = {}  # the operator's names of the anchors pinned, as the server's
    for k, anchor in enumerate(known_anchors(sim)):
        index = tracker.pin_anchor(
            np.array(anchor.position), anchor_type_index(anchor.type), level=anchor.level
        )
        known[f"known-{k}"] = index
    ctx = building_context("simulated", tracker, known, None, None)
    tally = None
    if options.zones:
        ids, rings, zone_levels = room_zones(sim.world)
        tracker.zones.set_zones(ids, rings, zone_levels, [None] * len(ids))
        tally = ZoneTally(tracker.zones.zones, ids)
    users = {device_id(u): u for u in range(len(sim.users))}
    liars = liar_devices(len(sim.users), options.liars) if options.liars else set()
    score = _Score(sim, users)
    for batch in lying(simulated_batches(sim, "simulated"), liars):
        user_batch = to_user_batch(batch, ctx).user_batch
        outcome = tracker.apply([user_batch])
        score.outcome(outcome)
        if tally is not None:
            for e in outcome.zone_events:
                tally.told(e.user, e.zone_id, e.kind, e.t_ms, e.told_ms)
        if progress is not None:
            progress(1)
        if not batch.steps or not tracker.is_placed(user_batch.user) or batch.device_id in liars:
            continue
        if options.mode == "pdr":
            xy, t_ms = tracker.dead_reckoning(user_batch.user), tracker.last_time_ms(user_batch.user)
            floor = tracker.floor_of(user_batch.user)[0]
        else:
            row = outcome.estimates[user_batch.user]
            xy, t_ms, floor = np.array([row.x, row.y]), row.t_ms, row.floor
        assert xy is not None
        score.estimate(users[user_batch.user], xy, t_ms, floor)
        if tally is not None:
            u, t = users[user_batch.user], (t_ms - EPOCH_MS) / 1000.0
            tally.sample(user_batch.user, t_ms, sim.true_position(u, t), sim.true_level(u, t), xy, floor)
    errors = np.array(score.errors)
    n_users = len(sim.users)
    expected = scenario.raw.get("expected_statistics", {})
    result: dict[str, Any] = {
        "mode": options.mode,
        "seed": options.seed,
        "filter_seed": options.tracker_seed,
        "liars": options.liars,
        "sampling": options.sampling,
        "particles": options.particles,
        "motion_model": options.motion_model,
        "crowd_solver": options.crowd_solver,
        "fingerprints": params.fingerprints.enabled,
        **error_summary(errors),
        "n_estimates": int(errors.size),
        "anchors_passed_per_user": sim.anchors_passed_per_user,
        "encounters_per_user": meetings_per_user(
            np.array(score.chosen_t), np.array(score.chosen_a), np.array(score.chosen_b), n_users
        ),
        "encounter_detections_per_user": 2 * score.detections / n_users,
        "encounters_chosen_per_user": 2 * len(score.chosen_t) / n_users,
        "encounters_applied_per_user": 2 * len(score.range_error) / n_users,
        "fingerprint_fixes_per_user": score.fingerprint_fixes / n_users,
        "expected_anchors_passed_per_user": expected.get("building_anchors_passed_per_user"),
        "expected_encounters_per_user": expected.get("encounters_per_user"),
    }
    if options.mode != "pdr":
        crowd_means = tracker.crowd.means()
        result.update(
            map_quality(
                np.array(score.joined_crowd, dtype=np.int64),
                np.array(score.joined_truth, dtype=np.int64),
                crowd_means,
                {k for k in crowd_means if tracker.crowd.anchor(k)[3]},
                sim.world.anchor_xy,
            )
        )
    if len(levels) > 1:
        result.update(score.floors())
    if score.range_error:
        result["encounter_true_distance_median_m"] = float(np.median(score.true_distance))
        result["encounter_range_bias_median_m"] = float(np.median(score.range_error))
    if tally is not None:
        result["zones"] = tally.result()
    result["seconds"] = time.perf_counter() - started
    return result, errors


def _share(count: int, total: int) -> float | None:
    return count / total if total else None


class _Score:
    """What one evaluation counts from the tracker's outcomes, against the simulated truth."""

    def __init__(self, sim: Simulation, users: dict[str, int]) -> None:
        self.sim = sim
        self.users = users
        self.errors: list[float] = []
        self.detections = 0
        self.fingerprint_fixes = 0
        self.chosen_t: list[float] = []
        self.chosen_a: list[int] = []
        self.chosen_b: list[int] = []
        self.range_error: list[float] = []
        self.true_distance: list[float] = []
        self.joined_crowd: list[int] = []
        self.joined_truth: list[int] = []
        # the true anchor of each building-anchor detection, by (user, phone time): the phones send a
        # detection at the time of the step that passed the anchor
        self._true_anchor: dict[tuple[int, int], int] = {}
        self.floor_t: list[list[float]] = [[] for _ in sim.users]
        self.floor_estimated: list[list[int]] = [[] for _ in sim.users]
        self.floor_true: list[list[int]] = [[] for _ in sim.users]
        for u, tr in enumerate(sim.users):
            for step, anchor in zip(tr.anchor_step.tolist(), tr.anchor_true.tolist(), strict=True):
                self._true_anchor[(u, EPOCH_MS + round(float(tr.t[step]) * 1000.0))] = int(anchor)

    def _seconds(self, t_ms: int) -> float:
        return (t_ms - EPOCH_MS) / 1000.0

    def estimate(self, user: int, xy: np.ndarray, t_ms: int, floor: int = 0) -> None:
        t = self._seconds(t_ms)
        truth = self.sim.true_position(user, t)
        self.errors.append(float(np.linalg.norm(xy - truth)))
        self.floor_t[user].append(t)
        self.floor_estimated[user].append(floor)
        self.floor_true[user].append(self.sim.true_level(user, t))

    def floors(self) -> dict[str, Any]:
        """The floor figures: the share of scored estimates on the right floor (all, with and without a
        barometer), and each change of floor's delay from the user's arrival to the first estimate on the new
        floor (unrecognised when none comes before the next change or the walk's end)."""
        right = {True: [0, 0], False: [0, 0]}
        delays: dict[str, list[float]] = {}
        for u, trace in enumerate(self.sim.users):
            t = np.array(self.floor_t[u])
            est = np.array(self.floor_estimated[u], dtype=np.int64)
            ok = est == np.array(self.floor_true[u], dtype=np.int64)
            tally = right[bool(trace.pressure.size)]
            tally[0] += int(ok.sum())
            tally[1] += int(ok.size)
            arrivals = [a for a, *_ in trace.transitions] + [math.inf]
            for k, (arrival, _, to, way) in enumerate(trace.transitions):
                seen = np.flatnonzero((t >= arrival) & (t < arrivals[k + 1]) & (est == to))
                delay = float(t[seen[0]] - arrival) if seen.size else math.inf
                delays.setdefault(way, []).append(delay)
                delays.setdefault("barometer" if trace.pressure.size else "no barometer", []).append(delay)
        every = [d for way in ("stairs", "lift", "escalator") for d in delays.get(way, [])]
        out: dict[str, Any] = {
            "right_floor": _share(right[True][0] + right[False][0], right[True][1] + right[False][1]),
            "right_floor_barometer": _share(*right[True]),
            "right_floor_no_barometer": _share(*right[False]),
            "floor_changes": len(every),
            "floor_changes_within_5s": _share(sum(d <= 5.0 for d in every), len(every)),
        }
        for name, values in sorted(delays.items()):
            key = name.replace(" ", "_")
            found = [d for d in values if math.isfinite(d)]
            out[f"floor_changes_{key}"] = len(values)
            out[f"floor_changes_{key}_within_5s"] = _share(sum(d <= 5.0 for d in values), len(values))
            out[f"floor_change_{key}_delay_p50_s"] = float(np.median(found)) if found else None
        return out

    def outcome(self, outcome: TrackerOutcome) -> None:
        self.detections += outcome.detections
        for name, report in outcome.reports.items():
            self.fingerprint_fixes += report.fingerprint_fixes
            for t_ms, crowd_id in report.anchor_joins:
                truth = self._true_anchor.get((self.users[name], t_ms))
                if truth is not None:
                    self.joined_crowd.append(crowd_id)
                    self.joined_truth.append(truth)
        for e in outcome.encounters:
            d = e.detection
            a, b = self.users[d.user_a], self.users[d.user_b]
            self.chosen_t.append(self._seconds(d.t_ms))
            self.chosen_a.append(a)
            self.chosen_b.append(b)
            if e.applied:
                t = self._seconds(d.t_ms)
                true = float(np.linalg.norm(self.sim.true_position(a, t) - self.sim.true_position(b, t)))
                self.true_distance.append(true)
                self.range_error.append(d.distance_m - true)
