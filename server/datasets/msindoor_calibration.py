"""Encounter-model calibration on a floor of Indoor Location 2.0 walks (``crowdslam calibrate``).

Every WiFi scan taken between a walk's first and last waypoint is placed by interpolating the surveyed
waypoints at the scan's time; cross-walk scan pairs are the labelled data (a pair is *near* within 5 m).
Entries whose last-seen time is more than ``stale_ap_ms`` before the scan are cached re-reports and are
dropped, as the live detector drops them. The report also gives the Weinberg constant that fits the floor's
surveyed walk lengths (``StepParams.weinberg_k``; a report, not applied). For each WiFi feature
(``slam_core.wifi.pairs``) the report gives precision and recall for near pairs; the paper's logarithmic
Sim-distance model (Figure 3) is fitted on the pairs Eq. 3 passes, with its empirical range variance, and
written as a calibration the server and ``crowdslam evaluate --calibration`` load. The walks carry no
phone-to-phone Bluetooth, so the Bluetooth model is kept from the base calibration (said in the report).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from server.datasets.msindoor import read_floor, read_trace
from slam_core.encounters.models import (
    FIT_MAX_DISTANCE_M,
    Calibration,
    WifiEq3Params,
    WifiFingerprintParams,
    fit_range_model,
)
from slam_core.encounters.selection import SelectionParams
from slam_core.sensing.pdr.online import ImuSamples, PdrParams, PdrState, pdr_steps
from slam_core.signalslam.windows import rss_matrix
from slam_core.wifi.pairs import (
    STALE_AP_MS,
    dense_eq3_matrix,
    fingerprint_matrix,
    precision_at_recall,
    precision_recall,
)

NEAR_M = 5.0


@dataclass(frozen=True)
class LabelledScans:
    rss: np.ndarray  # (S, A) dBm, NaN = not heard (or a stale cached entry)
    xy: np.ndarray  # (S, 2) surveyed position at the scan's time
    walk: np.ndarray  # (S,) walk index


@dataclass(frozen=True)
class Pairs:
    distance: np.ndarray
    features: dict[str, np.ndarray]


def labelled_scans(floor_dir: Path, stale_ap_ms: int = STALE_AP_MS) -> LabelledScans:
    ap_index: dict[str, int] = {}
    rows: list[dict[int, float]] = []
    xy: list[np.ndarray] = []
    walk: list[int] = []
    for w, path in enumerate(read_floor(floor_dir).traces):
        trace = read_trace(path)
        wp = trace.waypoints
        if len(wp) < 2:
            continue
        for scan in trace.wifi:
            if not wp[0, 0] <= scan.t_ms <= wp[-1, 0]:
                continue
            fresh = (scan.last_seen_ms <= 0) | (scan.last_seen_ms >= scan.t_ms - stale_ap_ms)
            entry = {
                ap_index.setdefault(scan.bssid[i].lower(), len(ap_index)): float(scan.rssi_dbm[i])
                for i in np.flatnonzero(fresh)
            }
            if not entry:
                continue
            rows.append(entry)
            xy.append(np.array([np.interp(scan.t_ms, wp[:, 0], wp[:, k]) for k in (1, 2)]))
            walk.append(w)
    return LabelledScans(
        rss_matrix(rows, len(ap_index)), np.array(xy).reshape(-1, 2), np.array(walk, dtype=np.int64)
    )


def weinberg_fit(floor_dir: Path, params: PdrParams | None = None) -> dict[str, float]:
    """The Weinberg constant that makes the median walk's step sum equal its surveyed length (between its
    first and last waypoints), and the spread of that ratio across walks (what the bias-scale filter
    absorbs)."""
    params = params or PdrParams()
    ratios = []
    for path in read_floor(floor_dir).traces:
        trace = read_trace(path)
        acc, rv, wp = (
            trace.streams.get("accelerometer"),
            trace.streams.get("rotation_vector"),
            trace.waypoints,
        )
        if acc is None or rv is None or len(acc) == 0 or len(rv) == 0 or len(wp) < 2:
            continue
        steps = pdr_steps(
            PdrState(), ImuSamples(acc, rv=np.column_stack([rv, np.full(len(rv), np.nan)])), params
        )
        inside = (steps.t_ms > wp[0, 0]) & (steps.t_ms <= wp[-1, 0])
        walked = float(np.sum(np.linalg.norm(np.diff(wp[:, 1:], axis=0), axis=1)))
        if walked > 5.0 and inside.sum() >= 5:
            ratios.append(walked / float(steps.length_m[inside].sum()))
    if not ratios:
        raise ValueError(f"{floor_dir}: no walk to fit the step length on")
    return {
        "weinberg_k": params.steps.weinberg_k * float(np.median(ratios)),
        "current_weinberg_k": params.steps.weinberg_k,
        "walk_scale_log_sd": float(np.std(np.log(ratios))),
        "walks": len(ratios),
    }


def cross_walk_pairs(scans: LabelledScans, eq3: WifiEq3Params) -> Pairs:
    """Every pair of scans from different walks, with its surveyed distance and both features."""
    if scans.rss.shape[0] < 2:
        raise ValueError("fewer than two placed WiFi scans: nothing to calibrate on")
    i, j = np.triu_indices(scans.rss.shape[0], k=1)
    other = scans.walk[i] != scans.walk[j]
    i, j = i[other], j[other]
    distance = np.linalg.norm(scans.xy[i] - scans.xy[j], axis=1)
    eq3_sim = dense_eq3_matrix(scans.rss, eq3.strongest_n, eq3.min_common)[i, j]
    fingerprint = fingerprint_matrix(scans.rss)[i, j]
    return Pairs(distance, {"eq3": eq3_sim, "fingerprint": fingerprint})


def calibrate_floor(
    floor_dir: Path, base: Calibration, eq3: WifiEq3Params | None = None
) -> tuple[Calibration, dict[str, Any], Pairs]:
    """The fitted calibration, the report (precision and recall per feature) and the labelled pairs."""
    eq3 = eq3 or WifiEq3Params()
    scans = labelled_scans(floor_dir)
    pairs = cross_walk_pairs(scans, eq3)
    near = pairs.distance <= NEAR_M
    if not near.any():
        raise ValueError(
            f"{floor_dir}: no two scans of different walks lie within {NEAR_M:g} m of each other, so "
            "there is nothing to calibrate the encounter models on (more walks are needed)"
        )
    report: dict[str, Any] = {
        "floor": str(floor_dir),
        "scans": int(scans.rss.shape[0]),
        "access_points": int(scans.rss.shape[1]),
        "cross_walk_pairs": int(pairs.distance.size),
        "near_pairs": int(near.sum()),
        "near_m": NEAR_M,
        "stale_ap_ms": STALE_AP_MS,
        "bluetooth": "kept from the base calibration (the walks have no phone-to-phone Bluetooth)",
    }
    for name, score in pairs.features.items():
        precision, threshold = precision_at_recall(score, near, 0.5)
        report[f"{name}_precision_at_recall_0.5"] = precision
        report[f"{name}_threshold_at_recall_0.5"] = threshold
    passing = pairs.features["eq3"] < eq3.threshold_db
    report["eq3_at_paper_threshold"] = {
        "threshold_db": eq3.threshold_db,
        "precision": float(near[passing].mean()) if passing.any() else math.nan,
        "recall": float(passing[near].mean()),
        "passing_median_distance_m": float(np.median(pairs.distance[passing])) if passing.any() else math.nan,
    }
    # fitted where encounters are used; R floors from the pairs the tracker would apply (detected, and
    # within the selection range of each other)
    used = pairs.distance <= SelectionParams().select_range_m
    finite = np.isfinite(pairs.features["eq3"])
    model = fit_range_model(
        pairs.features["eq3"][finite], pairs.distance[finite], "wifi-log", FIT_MAX_DISTANCE_M
    )
    model = model.with_empirical_variance(
        pairs.features["eq3"][passing & used], pairs.distance[passing & used]
    )
    report["wifi_model"] = {"coefficients": list(model.coefficients), "sigma_db": model.sigma}
    fingerprint = pairs.features["fingerprint"]
    strict = fingerprint < WifiFingerprintParams().threshold_db
    finite = np.isfinite(fingerprint)
    fingerprint_model = fit_range_model(
        fingerprint[finite], pairs.distance[finite], "wifi-log", FIT_MAX_DISTANCE_M
    )
    if (strict & used).sum() >= 30:
        fingerprint_model = fingerprint_model.with_empirical_variance(
            fingerprint[strict & used], pairs.distance[strict & used]
        )
    report["wifi_fingerprint_model"] = {
        "coefficients": list(fingerprint_model.coefficients),
        "sigma_db": fingerprint_model.sigma,
        "threshold_db": WifiFingerprintParams().threshold_db,
        "pairs_passing": int(strict.sum()),
        "precision_at_threshold": float(near[strict].mean()) if strict.any() else math.nan,
    }
    report["step_length"] = weinberg_fit(floor_dir)
    return replace(base, wifi=model, wifi_fingerprint=fingerprint_model), report, pairs


def plot_calibration(path: Path, pairs: Pairs, report: dict[str, Any]) -> None:
    """Precision-recall of each feature for near pairs, and Eq. 3 against surveyed distance."""
    # deferred: matplotlib loads only when plotting, its backend chosen before pyplot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    near = pairs.distance <= NEAR_M
    fig, (pr, scatter) = plt.subplots(1, 2, figsize=(11, 4.5), dpi=110)
    for name, score in pairs.features.items():
        _, precision, recall = precision_recall(score, near)
        pr.plot(recall, precision, label=f"{name} (P@R0.5 {report[f'{name}_precision_at_recall_0.5']:.2f})")
    pr.axvline(0.5, color="grey", lw=0.8, ls=":")
    pr.set_xlabel(f"recall (pairs within {NEAR_M:g} m)")
    pr.set_ylabel("precision")
    pr.set_xlim(0, 1)
    pr.set_ylim(0, 1)
    pr.grid(alpha=0.3)
    pr.legend()
    sim = pairs.features["eq3"]
    finite = np.isfinite(sim)
    pick = np.flatnonzero(finite)
    pick = pick[np.random.default_rng(0).permutation(pick.size)[:20_000]]
    scatter.scatter(pairs.distance[pick], sim[pick], s=2, alpha=0.3)
    a, b = report["wifi_model"]["coefficients"][:2]
    d = np.linspace(0.5, max(float(pairs.distance[pick].max(initial=1.0)), 1.0), 200)
    scatter.plot(d, a + b * np.log(d), color="C3", label="Sim = a + b ln d")
    scatter.set_xlabel("surveyed distance (m)")
    scatter.set_ylabel("Eq. 3 Sim (dB)")
    scatter.grid(alpha=0.3)
    scatter.legend()
    fig.suptitle(str(report["floor"]))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
