"""Encounters in a simulated world: the range models' calibration on labelled pairs, and meetings counted.

The paper's models (Eq. 3 for WiFi, RSS for Bluetooth) are fitted on the simulated scans and RSS of pairs
whose true distance is known, on a separate simulated world (another seed), as the paper calibrated its
models by experiment before deployment (Figures 2-3). The tracker then detects encounters itself, from the
phones' batches, and never sees a true distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_core.encounters.models import (
    FIT_MAX_DISTANCE_M,
    BluetoothParams,
    Calibration,
    WifiEq3Params,
    fit_range_model,
    wifi_eq3_similarity,
)
from slam_core.encounters.selection import SelectionParams
from slam_core.sim.simulation import Scenario, Simulation, simulate

CALIBRATION_SEED_OFFSET = 10_007
CALIBRATION_MIN_USERS = 23
"""The labelled-pair experiment that fits the range models walks at least the paper testbed's 23 phones:
the models belong to the radio environment, not to how many users the evaluated world holds (the density
sweep's sparsest world has 2, whose twin gave no WiFi pair to fit)."""
SCAN_PAIR_WINDOW_S = 1.0
MEETING_GAP_S = 30.0
"""Detections of a pair less than 30 s apart belong to one meeting (``encounters_per_user`` counts
meetings, the paper's 'encountering other users (7 on average)')."""


@dataclass(frozen=True)
class Candidates:
    t: np.ndarray
    a: np.ndarray
    b: np.ndarray
    feature: np.ndarray  # Sim (dB) for WiFi, RSS (dBm) for Bluetooth
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


BT_SMOOTHING_S = 1.0
"""Bluetooth RSS is averaged per pair over one sighting period, both directions (two readings of 4 dB noise
each on the testbed). A longer window blurs the range of pairs walking towards each other (with 4 s, the
fit's residual at 0-2 m was 8 dB). Encounters are chosen on the filters' estimates, not on the reading
(``slam_core.encounters.selection``), so a lucky strong reading from far away needs no longer window."""


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


def calibrate(scenario: Scenario, seed: int, selection: SelectionParams | None = None) -> Calibration:
    """Fit the paper's range models on a separate simulated world (labelled pairs, as Figures 2-3).

    Each model is fitted on the pairs within ``FIT_MAX_DISTANCE_M``. Its R floors are measured on the
    readings the tracker will apply: those passing the model's detection rule from pairs within the
    selection range (the calibration world's stand-in for 'the filters place them that close')."""
    selection = selection or SelectionParams()
    users = max(int(scenario["users"]["count"]), CALIBRATION_MIN_USERS)
    sim = simulate(scenario.with_setting("users", "count", users), seed + CALIBRATION_SEED_OFFSET)
    wifi = wifi_candidates(sim, WifiEq3Params(), threshold=math.inf)
    bt = bluetooth_candidates(sim, BluetoothParams(), cutoff=-math.inf)
    wifi_model = fit_range_model(wifi.feature, wifi.true_distance, "wifi-log", FIT_MAX_DISTANCE_M)
    bt_model = fit_range_model(bt.feature, bt.true_distance, "bt-quadratic", FIT_MAX_DISTANCE_M)
    near = selection.select_range_m
    wifi_used = (wifi.feature < WifiEq3Params().threshold_db) & (wifi.true_distance <= near)
    bt_used = (bt.feature >= BluetoothParams().cutoff_dbm) & (bt.true_distance <= near)
    return Calibration(
        wifi_model.with_empirical_variance(wifi.feature[wifi_used], wifi.true_distance[wifi_used]),
        bt_model.with_empirical_variance(bt.feature[bt_used], bt.true_distance[bt_used]),
    )


def meetings_per_user(t: np.ndarray, a: np.ndarray, b: np.ndarray, n_users: int) -> float:
    """Meetings (runs of a pair's encounters at times ``t`` (s), users ``a`` and ``b``, less than
    MEETING_GAP_S apart) per user, each counted for both users."""
    last: dict[tuple[int, int], float] = {}
    meetings = 0
    for ti, ai, bi in zip(t.tolist(), a.tolist(), b.tolist(), strict=True):
        pair = (int(min(ai, bi)), int(max(ai, bi)))
        if ti - last.get(pair, -math.inf) >= MEETING_GAP_S:
            meetings += 1
        last[pair] = float(ti)
    return 2 * meetings / n_users
