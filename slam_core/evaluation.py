"""Simulated evaluation: run a scenario through PDR, SemanticSLAM or DynamicSLAM and score every step.

Encounters are detected from the simulated scans and RSS by the paper's models, never from ground-truth
distances. Their distance fits are calibrated on a separate simulated world (another seed), as the paper
calibrated its models by experiment before deployment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam_core.crowd_graph import CrowdGraph, GraphParams
from slam_core.crowd_map import CrowdMapBuilder
from slam_core.encounters import (
    BluetoothParams,
    Calibration,
    WifiEq3Params,
    fit_range_model,
    wifi_eq3_similarity,
)
from slam_core.fastslam import DynamicSlam
from slam_core.metrics import error_summary
from slam_core.params import FilterParams, HumanAnchorParams, MotionParams
from slam_core.simulate import Scenario, Simulation, simulate

MODES = ("pdr", "semanticslam", "dynamicslam")
CALIBRATION_SEED_OFFSET = 10_007
SCAN_PAIR_WINDOW_S = 1.0
PAIR_COOLDOWN_S = 30.0
"""One encounter per pair and model per 30 s: successive detections of a pair walking together share its
errors, and applying them all double counts (it collapsed particle diversity: 700 updates/user, 3.2 m)."""
MAX_ENCOUNTER_SIGMA_M = 5.0
"""Only encounters whose calibrated range error is at most 5 m are applied; weaker ones carry little
information and, repeated, mostly add double counting. With these two rules the testbed yields about 7
encounters per user, the paper's figure."""
TICK_S = 0.5
CROWD_SOLVERS = ("fusion", "graph")
GRAPH_SOLVE_PERIOD_S = 5.0
"""The joint crowd-map solve runs at most every 5 s of walking time (it takes ~0.1 s)."""


@dataclass(frozen=True)
class Candidates:
    t: np.ndarray
    a: np.ndarray
    b: np.ndarray
    feature: np.ndarray  # Sim (dB) for WiFi, RSS (dBm) for Bluetooth
    true_distance: np.ndarray


@dataclass(frozen=True)
class Encounters:
    t: np.ndarray
    a: np.ndarray
    b: np.ndarray
    distance: np.ndarray
    variance: np.ndarray
    model: np.ndarray  # 0 WiFi, 1 Bluetooth
    true_distance: np.ndarray


def wifi_candidates(sim: Simulation, params: WifiEq3Params, threshold: float | None = None) -> Candidates:
    """Scan pairs of different users within SCAN_PAIR_WINDOW_S whose Eq. 3 similarity is below the
    threshold (default: the model's; ``inf`` keeps every comparable pair, for calibration)."""
    limit = params.threshold_db if threshold is None else threshold
    rows: list[tuple[float, int, int, float, float]] = []
    users = sim.users
    for i in range(len(users)):
        for j in range(i + 1, len(users)):
            ti, tj = users[i].scan_t, users[j].scan_t
            for ci, t in enumerate(ti):
                k = int(np.searchsorted(tj, t))
                for cj in (k - 1, k):
                    if 0 <= cj < len(tj) and abs(tj[cj] - t) <= SCAN_PAIR_WINDOW_S:
                        s, _ = wifi_eq3_similarity(users[i].scan_rss[ci], users[j].scan_rss[cj], params)
                        if s < limit:
                            tt = max(t, tj[cj])
                            d = float(np.linalg.norm(sim.true_position(i, tt) - sim.true_position(j, tt)))
                            rows.append((tt, i, j, s, d))
    return _candidates(rows)


BT_SMOOTHING_S = 4.0
"""Bluetooth RSS is averaged per pair (both directions) over the last 4 s before it is used: single
readings carry 4 dB of noise, and since far pairs vastly outnumber close ones, a lucky strong reading from
far away is the commonest strong reading. The paper low-passes its sensor streams for the same reason."""


def bluetooth_candidates(sim: Simulation, params: BluetoothParams, cutoff: float | None = None) -> Candidates:
    """Sightings whose pair-averaged RSS is above the cut-off; the feature is that average (dBm)."""
    limit = params.cutoff_dbm if cutoff is None else cutoff
    rows = []
    history: dict[tuple[int, int], list[tuple[float, float]]] = {}
    for t, (rx, tx), rss in zip(sim.bt_t, sim.bt_pair, sim.bt_rss, strict=True):
        pair = (int(min(rx, tx)), int(max(rx, tx)))
        recent = [(ts, r) for ts, r in history.get(pair, []) if t - ts < BT_SMOOTHING_S]
        recent.append((float(t), float(rss)))
        history[pair] = recent
        smoothed = float(np.mean([r for _, r in recent]))
        if smoothed >= limit:
            d = float(np.linalg.norm(sim.true_position(int(rx), t) - sim.true_position(int(tx), t)))
            rows.append((float(t), int(rx), int(tx), smoothed, d))
    return _candidates(rows)


def _candidates(rows: list[tuple[float, int, int, float, float]]) -> Candidates:
    if not rows:
        z = np.zeros(0)
        return Candidates(z, z.astype(np.int64), z.astype(np.int64), z, z)
    arr = np.array(rows)
    order = np.argsort(arr[:, 0], kind="stable")
    arr = arr[order]
    return Candidates(arr[:, 0], arr[:, 1].astype(np.int64), arr[:, 2].astype(np.int64), arr[:, 3], arr[:, 4])


def calibrate(scenario: Scenario, seed: int) -> Calibration:
    """Fit the paper's range models on a separate simulated world (labelled pairs, as Figures 2-3)."""
    sim = simulate(scenario, seed + CALIBRATION_SEED_OFFSET)
    wifi = wifi_candidates(sim, WifiEq3Params(), threshold=math.inf)
    bt = bluetooth_candidates(sim, BluetoothParams(), cutoff=-math.inf)
    wifi_model = fit_range_model(wifi.feature, wifi.true_distance, "wifi-log")
    bt_model = fit_range_model(bt.feature, bt.true_distance, "bt-quadratic")
    # empirical R on the pairs each model will actually report (those passing its threshold)
    wifi_pass = wifi.feature < WifiEq3Params().threshold_db
    bt_pass = bt.feature >= BluetoothParams().cutoff_dbm
    return Calibration(
        wifi_model.with_empirical_variance(wifi.feature[wifi_pass], wifi.true_distance[wifi_pass]),
        bt_model.with_empirical_variance(bt.feature[bt_pass], bt.true_distance[bt_pass]),
    )


def detect_encounters(sim: Simulation, calibration: Calibration) -> Encounters:
    """Both models' detections, at most one per pair and model every PAIR_COOLDOWN_S."""
    parts = []
    for code, cands, fit in (
        (0, wifi_candidates(sim, WifiEq3Params()), calibration.wifi),
        (1, bluetooth_candidates(sim, BluetoothParams()), calibration.bluetooth),
    ):
        last: dict[tuple[int, int], float] = {}
        keep = []
        for k in range(len(cands.t)):
            pair = (min(cands.a[k], cands.b[k]), max(cands.a[k], cands.b[k]))
            if cands.t[k] - last.get(pair, -math.inf) >= PAIR_COOLDOWN_S:
                last[pair] = cands.t[k]
                keep.append(k)
        idx = np.array(keep, dtype=np.int64)
        distance, variance = fit.range_and_variance(cands.feature[idx])
        informative = variance <= MAX_ENCOUNTER_SIGMA_M**2
        idx, distance, variance = idx[informative], distance[informative], variance[informative]
        parts.append(
            (
                cands.t[idx],
                cands.a[idx],
                cands.b[idx],
                distance,
                variance,
                np.full(idx.size, code),
                cands.true_distance[idx],
            )
        )
    cols = [np.concatenate([p[i] for p in parts]) for i in range(7)]
    order = np.argsort(cols[0], kind="stable")
    t, a, b, d, v, m, td = (c[order] for c in cols)
    return Encounters(t, a.astype(np.int64), b.astype(np.int64), d, v, m.astype(np.int64), td)


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
    crowd = CrowdMapBuilder(params.anchors.type_posterior, params.anchors.detection_sigma_m, fuse=fuse)
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
) -> dict[str, Any]:
    """Metrics of one run (see ``run_scenario_with_errors``)."""
    return run_scenario_with_errors(scenario, seed, mode, sampling, particles, motion_model, crowd_solver)[0]


def run_scenario_with_errors(
    scenario: Scenario,
    seed: int,
    mode: str,
    sampling: str = "iterative",
    particles: int = 75,
    motion_model: str = "bias-scale",
    crowd_solver: str = "graph",
) -> tuple[dict[str, Any], np.ndarray]:
    """Run the scenario; returns the metrics and the error of every step of every user (metres).
    ``crowd_solver``: "graph" re-solves the shared anchor map jointly (``slam_core.crowd_graph``);
    "fusion" fuses each detection's filtered estimate (``slam_core.crowd_map``)."""
    if crowd_solver not in CROWD_SOLVERS:
        raise ValueError(f"unknown crowd solver {crowd_solver!r}; valid: {', '.join(CROWD_SOLVERS)}")
    params = filter_params(mode, sampling, particles, motion_model)
    sim = simulate(scenario, seed)
    encounters = detect_encounters(sim, calibrate(scenario, seed)) if mode == "dynamicslam" else None
    if mode == "pdr":
        errors, best_errors = _dead_reckoning_errors(sim), None
        applied = 0
    else:
        errors, best_errors, _, applied = _filter_errors(sim, params, seed, encounters, crowd_solver)
    n_users = len(sim.users)
    detected = 0 if encounters is None else 2 * len(encounters.t) / n_users
    result: dict[str, Any] = {
        "mode": mode,
        "seed": seed,
        "sampling": sampling,
        "particles": particles,
        "motion_model": motion_model,
        "crowd_solver": crowd_solver,
        **error_summary(errors),
        "n_estimates": int(errors.size),
        "anchors_passed_per_user": sim.anchors_passed_per_user,
        "encounters_per_user": detected,
        "encounters_applied_per_user": 2 * applied / n_users,
        "expected_anchors_passed_per_user": scenario.raw.get("expected_statistics", {}).get(
            "building_anchors_passed_per_user"
        ),
        "expected_encounters_per_user": scenario.raw.get("expected_statistics", {}).get(
            "encounters_per_user"
        ),
    }
    if encounters is not None and len(encounters.t):
        result["encounter_true_distance_median_m"] = float(np.median(encounters.true_distance))
    if best_errors is not None:
        result["best_particle_median_m"] = float(np.median(best_errors))
    return result, errors


def _dead_reckoning_errors(sim: Simulation) -> np.ndarray:
    errors = []
    for tr in sim.users:
        steps = tr.step_length_obs[:, None] * np.column_stack(
            [np.cos(tr.step_heading_obs), np.sin(tr.step_heading_obs)]
        )
        path = tr.start_fix + np.cumsum(steps, axis=0)
        errors.append(np.linalg.norm(path - tr.xy[1:], axis=1))
    return np.concatenate(errors)


def _filter_errors(
    sim: Simulation,
    params: FilterParams,
    seed: int,
    encounters: Encounters | None,
    crowd_solver: str = "graph",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Errors of the weighted mean and of the max-weight particle at every step, the user of each error,
    and how many encounters were applied."""
    engine = DynamicSlam(params, seed=seed, initial_capacity=len(sim.users))
    crowd = crowd_with_known_anchors(sim, params, fuse=crowd_solver == "fusion")
    crowd_size = len(crowd)
    graph = CrowdGraph(GraphParams(detection_sigma_m=params.anchors.detection_sigma_m))
    for k in np.flatnonzero(sim.world.anchor_known):
        graph.set_known(int(k), sim.world.anchor_xy[k])
    displacement = np.zeros((len(sim.users), 2))
    walked = np.zeros(len(sim.users))
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
    enc_tick = (
        np.floor(encounters.t / TICK_S).astype(np.int64) if encounters is not None else np.zeros(0, np.int64)
    )
    errors: list[float] = []
    best_errors: list[float] = []
    error_users: list[int] = []
    applied = 0
    for tick in np.unique(np.concatenate([step_tick, enc_tick])):
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
            for u, k, length, heading in zip(users_sorted, step_index[sel], lengths, headings, strict=True):
                displacement[u] += length * np.array([np.cos(heading), np.sin(heading)])
                walked[u] += length
                if k in anchor_at[u]:
                    det_users.append(int(u))
                    det_types.append(anchor_at[u][k])
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
                if crowd_solver == "graph":
                    for u, c in zip(det_users, ids, strict=True):
                        graph.add_detection(u, int(c), displacement[u], float(walked[u]))
                if crowd_solver == "graph" and tick * TICK_S - last_solve_s >= GRAPH_SOLVE_PERIOD_S:
                    last_solve_s = tick * TICK_S
                    means, covs = graph.solve(crowd.means())
                    for c, mean in means.items():
                        crowd.set_estimate(c, mean, covs[c])
                    engine.refresh_crowd_anchors(engine.active_users, crowd.snapshot())
                if len(crowd) != crowd_size:
                    crowd_size = len(crowd)
                    engine.merge_crowd_map(engine.active_users, crowd.snapshot())
        if encounters is not None and params.use_human_anchors:
            e = np.flatnonzero(enc_tick == tick)
            e = e[(slots[encounters.a[e]] >= 0) & (slots[encounters.b[e]] >= 0)]
            if e.size:
                outcome = engine.observe_encounters(
                    slots[encounters.a[e]],
                    slots[encounters.b[e]],
                    encounters.distance[e],
                    encounters.variance[e],
                )
                applied += int(outcome.applied.sum())
        if sel.size:
            last_of_user = {int(u): int(k) for u, k in zip(step_user[sel], step_index[sel], strict=True)}
            us = np.array(sorted(last_of_user))
            summary = engine.summaries(slots[us])
            truth = np.array([sim.users[u].xy[last_of_user[u]] for u in us])
            errors += np.linalg.norm(summary[:, 0:2] - truth, axis=1).tolist()
            error_users += us.tolist()
            best_errors += np.linalg.norm(summary[:, 5:7] - truth, axis=1).tolist()
    return np.array(errors), np.array(best_errors), np.array(error_users, dtype=np.int64), applied


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
    raw = {k: dict(v) if isinstance(v, dict) else v for k, v in scenario.raw.items()}
    area = raw["floor"]["width_m"] * raw["floor"]["height_m"]
    if kind == "density":
        raw["users"]["count"] = max(2, round(area / value))
    elif kind == "anchor-density":
        raw["building_anchors"]["count"] = max(
            raw["building_anchors"]["known_positions"], round(area / value)
        )
    return Scenario.from_dict(raw)
