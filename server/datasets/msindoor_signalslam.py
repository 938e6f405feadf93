"""``crowdslam signalslam`` on a floor of Indoor Location 2.0 walks: the SignalSLAM protocol.

Each walk's first and last waypoints are its landmarks (as the paper's NFC tags); the intermediate waypoints
score raw PDR, recalibrated PDR (Eq. 4), GraphSLAM (motion + landmark edges) and SignalSLAM (plus WiFi
signal edges, Eq. 7), all walks of the floor jointly. Then, leaving walks out in turn (``folds``), a WiFi
fingerprint map is built from the SignalSLAM trajectories of the other walks and the held-out walks' scans
are localised on its 5 m grid by weighted kNN and by KL kernel regression; the same with the surveyed
positions gives the bound.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from server.datasets.msindoor import Trace, read_floor, read_trace
from slam_core.sensing.pdr.heading import with_final_offset
from slam_core.sensing.pdr.online import ImuSamples, PdrParams, PdrState, pdr_steps
from slam_core.signalslam.graph import SignalGraphParams, Trajectories, Walk, position_at, solve
from slam_core.signalslam.maps import FingerprintGrid, fingerprint_grid, localise_kernel, localise_knn
from slam_core.signalslam.windows import (
    WINDOW_STEP_MS,
    rss_matrix,
    window_counts,
    window_mean_series,
    window_sightings,
)
from slam_core.wifi.pairs import STALE_AP_MS

KNN = 7
FINGERPRINT_CELL_M = 5.0


@dataclass(frozen=True)
class _Scans:
    t_ms: np.ndarray
    rss: list[dict[int, float]]  # fresh entries: AP column -> dBm


@dataclass(frozen=True)
class _Prepared:
    walk: Walk
    checkpoints: np.ndarray  # (K, 3) intermediate waypoints t, x, y
    waypoints: np.ndarray
    scans: _Scans
    beacons: tuple[np.ndarray, np.ndarray]  # sighting times, beacon columns
    magnetic: np.ndarray  # (M, 2) t, magnitude (uT)


def _fresh_scans(trace: Trace, ap_index: dict[str, int]) -> _Scans:
    times, rows = [], []
    for scan in trace.wifi:
        fresh = (scan.last_seen_ms <= 0) | (scan.last_seen_ms >= scan.t_ms - STALE_AP_MS)
        entry = {
            ap_index.setdefault(scan.bssid[i].lower(), len(ap_index)): float(scan.rssi_dbm[i])
            for i in np.flatnonzero(fresh)
        }
        if entry:
            times.append(scan.t_ms)
            rows.append(entry)
    return _Scans(np.array(times, dtype=np.int64), rows)


def _prepare(
    trace: Trace, ap_index: dict[str, int], beacon_index: dict[str, int], pdr: PdrParams
) -> _Prepared | None:
    wp = trace.waypoints
    acc, rv = trace.streams.get("accelerometer"), trace.streams.get("rotation_vector")
    gyr = trace.streams.get("gyroscope", np.zeros((0, 4)))
    if len(wp) < 2 or acc is None or rv is None or len(acc) == 0 or len(rv) == 0:
        return None
    rv5 = np.column_stack([rv, np.full(len(rv), np.nan)])
    steps = pdr_steps(PdrState(), ImuSamples(acc, gyr=gyr, rv=rv5), pdr)
    azimuths = with_final_offset(steps.azimuth_rad, steps.heading_offset_rad)  # offline: the whole walk
    inside = (steps.t_ms > wp[0, 0]) & (steps.t_ms <= wp[-1, 0])
    if inside.sum() < 2:
        return None
    scans = _fresh_scans(trace, ap_index)
    centres = np.arange(wp[0, 0], wp[-1, 0] + 1, WINDOW_STEP_MS)
    walk = Walk(
        t_ms=np.concatenate([[wp[0, 0]], steps.t_ms[inside]]).astype(np.int64),
        lengths=steps.length_m[inside],
        headings=np.pi / 2 - azimuths[inside],
        start=wp[0, 1:].copy(),
        end=wp[-1, 1:].copy(),
        window_t=centres.astype(np.int64),
        window_counts=np.zeros((centres.size, 0)),  # filled once every AP of the floor is indexed
    )
    beacon_t = np.array([b[0] for b in trace.beacons], dtype=np.int64)
    beacon_col = np.array(
        [beacon_index.setdefault(b[7].lower(), len(beacon_index)) for b in trace.beacons], dtype=np.int64
    )
    mag = trace.streams.get("magnetometer", np.zeros((0, 4)))
    magnetic = (
        np.column_stack([mag[:, 0], np.linalg.norm(mag[:, 1:4], axis=1)]) if len(mag) else np.zeros((0, 2))
    )
    return _Prepared(walk, wp[1:-1], wp, scans, (beacon_t, beacon_col), magnetic)


def _with_windows(p: _Prepared, n_aps: int, n_beacons: int) -> _Prepared:
    centres = p.walk.window_t
    counts = window_counts(centres, p.scans.t_ms, p.scans.rss, n_aps)
    beacons = window_sightings(centres, *p.beacons, n_beacons)
    magnetic = window_mean_series(centres, p.magnetic[:, 0], p.magnetic[:, 1])
    keep = counts.sum(axis=1) > 0
    walk = Walk(
        **{
            **p.walk.__dict__,
            "window_t": centres[keep],
            "window_counts": counts[keep],
            "window_beacons": beacons[keep],
            "window_magnetic": magnetic[keep],
        }
    )
    return _Prepared(walk, p.checkpoints, p.waypoints, p.scans, p.beacons, p.magnetic)


@dataclass(frozen=True)
class SignalSlamRun:
    result: dict[str, Any]
    prepared: list[_Prepared]
    trajectories: Trajectories
    ap_names: list[str]  # BSSID of each AP column


def run_signalslam(
    floor_dir: Path,
    params: SignalGraphParams | None = None,
    folds: int = 5,
    progress: Callable[[str], None] | None = None,
) -> SignalSlamRun:
    started = time.perf_counter()
    say = progress or (lambda _: None)
    ap_index: dict[str, int] = {}
    beacon_index: dict[str, int] = {}
    say("reading walks and dead reckoning")
    prepared = [
        p
        for path in read_floor(floor_dir).traces
        if (p := _prepare(read_trace(path), ap_index, beacon_index, PdrParams()))
    ]
    if not prepared:
        raise ValueError(f"{floor_dir}: no walk has an accelerometer, a rotation vector and two waypoints")
    prepared = [_with_windows(p, len(ap_index), len(beacon_index)) for p in prepared]
    say(f"optimising {len(prepared)} walks jointly (gtsam)")
    trajectories = solve([p.walk for p in prepared], params or SignalGraphParams())
    result: dict[str, Any] = {"floor": str(floor_dir), "walks": len(prepared)}
    for name in ("raw", "calibrated", "graphslam", "signalslam"):
        errors = _checkpoint_errors(prepared, getattr(trajectories, name))
        label = "pdr" if name == "raw" else name
        result[f"{label}_p50_m"] = float(np.percentile(errors, 50))
        result[f"{label}_p90_m"] = float(np.percentile(errors, 90))
        result["n_checkpoints"] = int(errors.size)
    say("fingerprint maps, leaving walks out")
    for source, positions in (("", trajectories.signalslam), ("_surveyed", None)):
        found = _fingerprint_errors(prepared, positions, len(ap_index), folds)
        for method, errors in found.items():
            name = {"knn": "fingerprint", "grid_knn": "fingerprint_grid", "grid_kl": "fingerprint_kl"}[method]
            result[f"{name}{source}_p50_m"] = float(np.percentile(errors, 50))
            result[f"{name}{source}_p90_m"] = float(np.percentile(errors, 90))
    result["seconds"] = time.perf_counter() - started
    names = sorted(ap_index, key=ap_index.__getitem__)
    return SignalSlamRun(result, prepared, trajectories, names)


def _checkpoint_errors(prepared: list[_Prepared], positions: list[np.ndarray]) -> np.ndarray:
    errors = []
    for p, xy in zip(prepared, positions, strict=True):
        if len(p.checkpoints):
            estimate = position_at(p.walk.t_ms, xy, p.checkpoints[:, 0])
            errors.append(np.linalg.norm(estimate - p.checkpoints[:, 1:], axis=1))
    if not errors:
        raise ValueError("no walk has an intermediate waypoint to score")
    return np.concatenate(errors)


def _scan_matrix(p: _Prepared, n_aps: int, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    keep = (p.scans.t_ms >= lo) & (p.scans.t_ms <= hi)
    return p.scans.t_ms[keep], rss_matrix([e for e, k in zip(p.scans.rss, keep, strict=True) if k], n_aps)


def _fingerprint_errors(
    prepared: list[_Prepared], positions: list[np.ndarray] | None, n_aps: int, folds: int
) -> dict[str, np.ndarray]:
    """Leave-walks-out WiFi localisation on a map of the other folds' scans placed by ``positions`` (None:
    surveyed positions): weighted kNN over the placed scans themselves (``knn``), and on their 5 m
    fingerprint grid by weighted kNN (``grid_knn``) and by KL kernel regression (``grid_kl``)."""
    placed, rss, truth, fold = [], [], [], []
    for i, p in enumerate(prepared):
        wp = p.waypoints
        t, scan_rss = _scan_matrix(p, n_aps, wp[0, 0], wp[-1, 0])
        surveyed = np.column_stack([np.interp(t, wp[:, 0], wp[:, k]) for k in (1, 2)])
        placed.append(surveyed if positions is None else position_at(p.walk.t_ms, positions[i], t))
        rss.append(scan_rss)
        truth.append(surveyed)
        fold.append(np.full(t.size, i % folds))
    xy, all_rss, all_truth, all_fold = (
        np.vstack(placed),
        np.vstack(rss),
        np.vstack(truth),
        np.concatenate(fold),
    )
    errors: dict[str, list[np.ndarray]] = {"knn": [], "grid_knn": [], "grid_kl": []}
    for f in range(folds):
        held = all_fold == f
        if not held.any() or held.all():
            continue
        heard = np.isfinite(all_rss[~held]).astype(float)
        scans = FingerprintGrid(xy[~held], all_rss[~held], heard, np.ones(heard.shape[0]))
        grid = fingerprint_grid(xy[~held], all_rss[~held], FINGERPRINT_CELL_M)
        for name, estimate in (
            ("knn", localise_knn(scans, all_rss[held], KNN)),
            ("grid_knn", localise_knn(grid, all_rss[held], KNN)),
            ("grid_kl", localise_kernel(grid, np.isfinite(all_rss[held]).astype(float))),
        ):
            ok = np.all(np.isfinite(estimate), axis=1)
            errors[name].append(np.linalg.norm(estimate[ok] - all_truth[held][ok], axis=1))
    return {name: np.concatenate(e) for name, e in errors.items()}
