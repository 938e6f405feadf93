"""Simulated evaluation: run a scenario through PDR, SemanticSLAM or DynamicSLAM and score every step.

Encounters are detected and their range models calibrated as ``slam_core.simulated_encounters`` does (the
paper's models on the simulated scans and RSS, never ground-truth distances); which of them are applied is
chosen during the run from the filters' own estimates, as the live tracker does
(``slam_core.evaluation_radio`` holds that stage and the fingerprint fixes).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

import slam_core.evaluation_radio as radio
from slam_core.crowd_fingerprints import CrowdFingerprints, FingerprintParams
from slam_core.crowd_graph import CrowdGraph, GraphParams
from slam_core.crowd_map import CrowdMapBuilder
from slam_core.encounter_selection import EncounterSelector, SelectionParams
from slam_core.encounters import Calibration
from slam_core.fastslam import DynamicSlam
from slam_core.map_quality import map_quality
from slam_core.metrics import error_summary
from slam_core.params import FilterParams, HumanAnchorParams, MotionParams
from slam_core.simulate import Scenario, Simulation, UserTrace, simulate
from slam_core.simulated_encounters import Encounters, calibrate, detect_encounters, meetings_per_user

MODES = ("pdr", "semanticslam", "dynamicslam")
TICK_S = 0.5
CROWD_SOLVERS = ("fusion", "graph")
GRAPH_SOLVE_PERIOD_S = 5.0
"""The joint crowd-map solve runs at most every 5 s of walking time (it takes ~0.1 s)."""


def filter_params(mode: str, sampling: str, particles: int, motion_model: str) -> FilterParams:
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; valid: {', '.join(MODES)}")
    return FilterParams(
        n_particles=particles,
        motion=MotionParams(model=motion_model),
        human=HumanAnchorParams(sampling=sampling),
        use_human_anchors=mode == "dynamicslam",
    )


def crowd_with_known_anchors(sim: Simulation, params: FilterParams, fuse: bool = True) -> CrowdMapBuilder:
    crowd = CrowdMapBuilder(
        params.anchors.type_posterior,
        params.anchors.detection_sigma_m,
        params.anchors.new_anchor_likelihood,
        fuse=fuse,
    )
    for k in np.flatnonzero(sim.world.anchor_known):
        crowd.add_known(sim.world.anchor_xy[k], int(sim.world.anchor_type[k]))
    return crowd


def run_scenario(
    scenario: Scenario,
    seed: int,
    mode: str,
    sampling: str = "iterative",
    particles: int = 75,
    motion_model: str = "bias-scale",
    crowd_solver: str = "graph",
    fingerprints: bool = True,
) -> dict[str, Any]:
    """Metrics of one run (see ``run_scenario_with_errors``)."""
    return run_scenario_with_errors(
        scenario, seed, mode, sampling, particles, motion_model, crowd_solver, fingerprints
    )[0]


def run_scenario_with_errors(
    scenario: Scenario,
    seed: int,
    mode: str,
    sampling: str = "iterative",
    particles: int = 75,
    motion_model: str = "bias-scale",
    crowd_solver: str = "graph",
    fingerprints: bool = True,
) -> tuple[dict[str, Any], np.ndarray]:
    """Run the scenario; returns the metrics and the error of every step of every user (metres).
    ``crowd_solver``: "graph" re-solves the shared anchor map jointly (``slam_core.crowd_graph``);
    "fusion" fuses each detection's filtered estimate (``slam_core.crowd_map``). ``fingerprints``: in
    dynamicslam mode, fixes on the crowd's WiFi fingerprint map as the server makes them by default (other
    users' scans, like human anchors: semanticslam does without)."""
    if crowd_solver not in CROWD_SOLVERS:
        raise ValueError(f"unknown crowd solver {crowd_solver!r}; valid: {', '.join(CROWD_SOLVERS)}")
    params = filter_params(mode, sampling, particles, motion_model)
    sim = simulate(scenario, seed)
    calibration = calibrate(scenario, seed) if mode == "dynamicslam" else None
    encounters = detect_encounters(sim, calibration) if calibration is not None else None
    with_fingerprints = fingerprints and mode == "dynamicslam"
    if mode == "pdr":
        errors, best_errors = _dead_reckoning_errors(sim), None
        run = None
    else:
        fp_params = FingerprintParams(enabled=True) if with_fingerprints else None
        run = _filter_errors(sim, params, seed, encounters, crowd_solver, calibration, None, fp_params)
        errors, best_errors = run.errors, run.best_errors
    n_users = len(sim.users)
    result: dict[str, Any] = {
        "mode": mode,
        "seed": seed,
        "sampling": sampling,
        "particles": particles,
        "motion_model": motion_model,
        "crowd_solver": crowd_solver,
        "fingerprints": with_fingerprints,
        **error_summary(errors),
        "n_estimates": int(errors.size),
        "anchors_passed_per_user": sim.anchors_passed_per_user,
        "encounters_per_user": 0.0 if encounters is None else meetings_per_user(encounters, n_users),
        "encounter_detections_per_user": 0.0 if encounters is None else 2 * len(encounters.t) / n_users,
        "encounters_chosen_per_user": 0.0 if run is None else 2 * run.chosen / n_users,
        "encounters_applied_per_user": 0.0 if run is None else 2 * run.applied.size / n_users,
        "fingerprint_fixes_per_user": 0.0 if run is None else run.fingerprint_fixes / n_users,
        **({} if run is None else run.map_scores),
        "expected_anchors_passed_per_user": scenario.raw.get("expected_statistics", {}).get(
            "building_anchors_passed_per_user"
        ),
        "expected_encounters_per_user": scenario.raw.get("expected_statistics", {}).get(
            "encounters_per_user"
        ),
    }
    if run is not None and run.applied.size:
        assert encounters is not None
        residual = encounters.distance[run.applied] - encounters.true_distance[run.applied]
        result["encounter_true_distance_median_m"] = float(np.median(encounters.true_distance[run.applied]))
        result["encounter_range_bias_median_m"] = float(np.median(residual))
    if best_errors is not None:
        result["best_particle_median_m"] = float(np.median(best_errors))
    return result, errors


def _dead_reckoned(tr: UserTrace) -> np.ndarray:
    """(S+1, 2) the user's observed steps summed from its start: its dead-reckoned displacement at each of
    its positions."""
    steps = tr.step_length_obs[:, None] * np.column_stack(
        [np.cos(tr.step_heading_obs), np.sin(tr.step_heading_obs)]
    )
    return np.vstack([np.zeros((1, 2)), np.cumsum(steps, axis=0)])


def _dead_reckoning_errors(sim: Simulation) -> np.ndarray:
    errors = [np.linalg.norm(tr.start_fix + _dead_reckoned(tr)[1:] - tr.xy[1:], axis=1) for tr in sim.users]
    return np.concatenate(errors)


@dataclass(frozen=True)
class FilterRun:
    errors: np.ndarray  # error of the weighted mean at every step of every user (m)
    best_errors: np.ndarray  # error of the max-weight particle (m)
    error_users: np.ndarray  # the user of each error
    chosen: int  # encounters chosen by the selector
    applied: np.ndarray  # indices (into the detections) of the encounters applied
    fingerprint_fixes: int = 0  # scans localised on the crowd fingerprint map and applied
    map_scores: dict[str, float | None] = field(default_factory=dict)  # the learned map against the truth


def _filter_errors(
    sim: Simulation,
    params: FilterParams,
    seed: int,
    encounters: Encounters | None,
    crowd_solver: str = "graph",
    calibration: Calibration | None = None,
    selection: SelectionParams | None = None,
    fingerprints: FingerprintParams | None = None,
) -> FilterRun:
    """Run the filters over the simulation, choosing which detected encounters to apply from the filters'
    own estimates (``slam_core.encounter_selection``), as the live tracker does; with ``fingerprints``
    enabled, each scan is also localised on the crowd's fingerprint map as the tracker does
    (``slam_core.tracker_radio.fingerprint_fixes``), after the tick's steps and before its encounters."""
    if encounters is not None and calibration is None:
        raise ValueError("encounters need the calibration whose range models reported them")
    selector = EncounterSelector(selection or SelectionParams())
    engine = DynamicSlam(params, seed=seed, initial_capacity=len(sim.users))
    crowd = crowd_with_known_anchors(sim, params, fuse=crowd_solver == "fusion")
    crowd_size = len(crowd)
    graph = CrowdGraph(GraphParams(detection_sigma_m=params.anchors.detection_sigma_m))
    for k in np.flatnonzero(sim.world.anchor_known):
        graph.set_known(int(k), sim.world.anchor_xy[k])
    last_solve_s = -np.inf
    slots = np.full(len(sim.users), -1, dtype=np.int64)
    # every step of every user as (tick, user, step index)
    step_user = np.concatenate([np.full(len(tr.t) - 1, u) for u, tr in enumerate(sim.users)])
    step_index = np.concatenate([np.arange(1, len(tr.t)) for tr in sim.users])
    step_time = np.concatenate([tr.t[1:] for tr in sim.users])
    step_tick = np.floor(step_time / TICK_S).astype(np.int64)
    anchor_at = [
        dict(zip(tr.anchor_step.tolist(), tr.anchor_detected_type.tolist(), strict=True)) for tr in sim.users
    ]
    true_anchor_at = [
        dict(zip(tr.anchor_step.tolist(), tr.anchor_true.tolist(), strict=True)) for tr in sim.users
    ]
    detection_crowd_ids: list[int] = []
    detection_true_anchors: list[int] = []
    enc_tick = (
        np.floor(encounters.t / TICK_S).astype(np.int64) if encounters is not None else np.zeros(0, np.int64)
    )
    fp = CrowdFingerprints(fingerprints) if fingerprints is not None and fingerprints.enabled else None
    scan_user = np.concatenate([np.full(len(tr.scan_t), u) for u, tr in enumerate(sim.users)])
    scan_index = np.concatenate([np.arange(len(tr.scan_t)) for tr in sim.users])
    scan_tick = np.floor(np.concatenate([tr.scan_t for tr in sim.users]) / TICK_S).astype(np.int64)
    if fp is None:
        scan_tick = np.zeros(0, np.int64)
    dead_reckoned = [_dead_reckoned(tr) for tr in sim.users]
    # each user's dead reckoning and distance walked after each step, and its steps applied so far
    walked_at = [np.concatenate([[0.0], np.cumsum(tr.step_length_obs)]) for tr in sim.users]
    steps_done = np.zeros(len(sim.users), dtype=np.int64)
    ap_names = [f"ap{i}" for i in range(sim.world.ap_xy.shape[0])]
    errors: list[float] = []
    best_errors: list[float] = []
    error_users: list[int] = []
    chosen = 0
    fingerprint_fixes = 0
    applied: list[np.ndarray] = []
    for tick in np.unique(np.concatenate([step_tick, enc_tick, scan_tick])):
        sel = np.flatnonzero(step_tick == tick)
        users_now = step_user[sel]
        for u in users_now[slots[users_now] < 0]:
            tr = sim.users[u]
            slots[u] = engine.add_user(
                tr.start_fix[0], tr.start_fix[1], tr.start_heading_fix, 0.5, crowd.snapshot()
            )
            graph.add_user(int(u), tr.start_fix)
        if sel.size:
            order = np.lexsort((step_index[sel], users_now))
            sel = sel[order]
            users_sorted = step_user[sel]
            uniq, counts = np.unique(users_sorted, return_counts=True)
            offsets = np.concatenate([[0], np.cumsum(counts)])
            lengths = np.array(
                [
                    sim.users[u].step_length_obs[k - 1]
                    for u, k in zip(users_sorted, step_index[sel], strict=True)
                ]
            )
            headings = np.array(
                [
                    sim.users[u].step_heading_obs[k - 1]
                    for u, k in zip(users_sorted, step_index[sel], strict=True)
                ]
            )
            engine.step(slots[uniq], offsets, lengths, headings)
            det_users, det_types = [], []
            for u, k in zip(users_sorted, step_index[sel], strict=True):
                steps_done[u] = k
                if k in anchor_at[u]:
                    det_users.append(int(u))
                    det_types.append(anchor_at[u][k])
                    detection_true_anchors.append(true_anchor_at[u][k])
            if det_users:
                # each detection feeds the crowd map with the user's pre-update estimate, then the filter
                before = engine.summaries(slots[det_users])
                ids = np.array(
                    [
                        crowd.contribute(
                            u, row[0:2], np.array([[row[2], row[3]], [row[3], row[4]]]), f, float(tick)
                        )
                        for u, row, f in zip(det_users, before, det_types, strict=True)
                    ]
                )
                engine.observe_building_anchors(slots[det_users], np.array(det_types), ids)
                detection_crowd_ids += ids.tolist()
                if crowd_solver == "graph":
                    for u, c in zip(det_users, ids, strict=True):
                        now = steps_done[u]
                        graph.add_detection(u, int(c), dead_reckoned[u][now], float(walked_at[u][now]))
                if crowd_solver == "graph" and tick * TICK_S - last_solve_s >= GRAPH_SOLVE_PERIOD_S:
                    last_solve_s = tick * TICK_S
                    means, covs = graph.solve(crowd.means())
                    for c, mean in means.items():
                        crowd.set_estimate(c, mean, covs[c])
                    engine.refresh_crowd_anchors(engine.active_users, crowd.snapshot())
                if len(crowd) != crowd_size:
                    crowd_size = len(crowd)
                    engine.merge_crowd_map(engine.active_users, crowd.snapshot())
        if fp is not None:
            assert fingerprints is not None
            s = np.flatnonzero(scan_tick == tick)
            fingerprint_fixes += radio.fingerprint_fixes(
                engine, fp, fingerprints, sim, slots, steps_done, dead_reckoned, ap_names,
                scan_user[s], scan_index[s],
            )  # fmt: skip
        if encounters is not None and calibration is not None and params.use_human_anchors:
            e = np.flatnonzero(enc_tick == tick)
            e = e[(slots[encounters.a[e]] >= 0) & (slots[encounters.b[e]] >= 0)]
            if e.size:
                offset, drift_var = radio.carried(sim, encounters, e, dead_reckoned, walked_at, steps_done)
                keep = radio.choose(engine, selector, slots, encounters, e, calibration, offset)
                e, offset, drift_var = e[keep], offset[keep], drift_var[keep]
                chosen += e.size
            if e.size:
                outcome = engine.observe_encounters(
                    slots[encounters.a[e]],
                    slots[encounters.b[e]],
                    encounters.distance[e],
                    encounters.variance[e] + drift_var,
                    offset,
                )
                applied.append(e[outcome.applied])
        if sel.size:
            last_of_user = {int(u): int(k) for u, k in zip(step_user[sel], step_index[sel], strict=True)}
            us = np.array(sorted(last_of_user))
            summary = engine.summaries(slots[us])
            truth = np.array([sim.users[u].xy[last_of_user[u]] for u in us])
            errors += np.linalg.norm(summary[:, 0:2] - truth, axis=1).tolist()
            error_users += us.tolist()
            best_errors += np.linalg.norm(summary[:, 5:7] - truth, axis=1).tolist()
    final_map = crowd.means()
    return FilterRun(
        np.array(errors),
        np.array(best_errors),
        np.array(error_users, dtype=np.int64),
        chosen,
        np.concatenate(applied) if applied else np.zeros(0, dtype=np.int64),
        fingerprint_fixes,
        map_quality(
            np.array(detection_crowd_ids, dtype=np.int64),
            np.array(detection_true_anchors, dtype=np.int64),
            final_map,
            {k for k in final_map if crowd.anchor(k)[3]},
            sim.world.anchor_xy,
        ),
    )


SWEEPS = ("particles", "density", "anchor-density")


def sweep_values(kind: str) -> list[float]:
    """The x axis of the paper's Figures 9 (particles), 11 (m^2 per user) and 13 (m^2 per anchor)."""
    if kind == "particles":
        return [1, 5, 10, 25, 50, 75, 100]
    if kind == "density":
        return [30, 60, 130, 300, 750, 1500]
    if kind == "anchor-density":
        return [100, 200, 400, 750, 1500]
    raise ValueError(f"unknown sweep {kind!r}; valid: {', '.join(SWEEPS)}")


def swept_scenario(scenario: Scenario, kind: str, value: float) -> Scenario:
    """The scenario with one quantity changed, as the paper's sweeps do (the rest stays as given)."""
    area = scenario["floor"]["width_m"] * scenario["floor"]["height_m"]
    if kind == "density":
        return scenario.with_setting("users", "count", max(2, round(area / value)))
    if kind == "anchor-density":
        count = max(scenario["building_anchors"]["known_positions"], round(area / value))
        return scenario.with_setting("building_anchors", "count", count)
    return scenario
