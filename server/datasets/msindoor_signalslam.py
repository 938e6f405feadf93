"""``crowdslam signalslam`` on a floor of Indoor Location 2.0 walks: the SignalSLAM protocol.

Each walk's first and last waypoints are its landmarks (as the paper's NFC tags); the intermediate waypoints
score raw PDR, recalibrated PDR (Eq. 4), GraphSLAM (motion + landmark edges) and SignalSLAM (plus WiFi
signal edges, Eq. 7), all walks of the floor jointly. Then, leaving walks out in turn (``folds``), a WiFi
fingerprint map is built from the SignalSLAM trajectories of the other walks and the held-out walks' scans
are localised by weighted kNN; the same with the surveyed positions gives the bound.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from server.datasets.msindoor import Trace, read_floor, read_trace
from slam_core.pdr.frontend import ImuSamples, PdrParams, PdrState, pdr_steps
from slam_core.signal_map.graph import GraphParams, Trajectories, Walk, position_at, solve
from slam_core.wifi_pairs import fingerprint_matrix

STALE_AP_MS = 3_000
WINDOW_MS = 10_000  # the paper's 10 s windows ...
WINDOW_STEP_MS = 1_000  # ... every second
KNN = 7


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
    if len(wp) < 2 or acc is None or rv is None or len(acc) == 0 or len(rv) == 0:
        return None
    rv5 = np.column_stack([rv, np.full(len(rv), np.nan)])
    steps = pdr_steps(PdrState(), ImuSamples(acc, rv=rv5), pdr)
    inside = (steps.t_ms > wp[0, 0]) & (steps.t_ms <= wp[-1, 0])
    if inside.sum() < 2:
        return None
    scans = _fresh_scans(trace, ap_index)
    centres = np.arange(wp[0, 0], wp[-1, 0] + 1, WINDOW_STEP_MS)
    walk = Walk(
        t_ms=np.concatenate([[wp[0, 0]], steps.t_ms[inside]]).astype(np.int64),
        lengths=steps.length_m[inside],
        headings=np.pi / 2 - steps.azimuth_rad[inside],
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
    half = WINDOW_MS // 2
    centres = p.walk.window_t
    counts = np.zeros((centres.size, n_aps))
    for t, entry in zip(p.scans.t_ms, p.scans.rss, strict=True):
        rows = np.flatnonzero(np.abs(centres - t) <= half)
        cols = np.array(list(entry), dtype=np.int64)
        counts[np.ix_(rows, cols)] += 1.0
    beacons = np.zeros((centres.size, n_beacons))
    beacon_t, beacon_col = p.beacons
    for t, col in zip(beacon_t, beacon_col, strict=True):
        beacons[np.abs(centres - t) <= half, col] += 1.0
    magnetic = np.full(centres.size, np.nan)
    if len(p.magnetic):
        lo = np.searchsorted(p.magnetic[:, 0], centres - half)
        hi = np.searchsorted(p.magnetic[:, 0], centres + half, side="right")
        sums = np.concatenate([[0.0], np.cumsum(p.magnetic[:, 1])])
        n = hi - lo
        magnetic = np.where(n > 0, (sums[hi] - sums[lo]) / np.maximum(n, 1), np.nan)
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


def run_signalslam(
    floor_dir: Path,
    params: GraphParams | None = None,
    folds: int = 5,
    progress: Callable[[str], None] | None = None,
) -> tuple[dict[str, Any], list[_Prepared], Trajectories]:
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
    trajectories = solve([p.walk for p in prepared], params or GraphParams())
    result: dict[str, Any] = {"floor": str(floor_dir), "walks": len(prepared)}
    for name in ("raw", "calibrated", "graphslam", "signalslam"):
        errors = _checkpoint_errors(prepared, getattr(trajectories, name))
        label = "pdr" if name == "raw" else name
        result[f"{label}_p50_m"] = float(np.percentile(errors, 50))
        result[f"{label}_p90_m"] = float(np.percentile(errors, 90))
        result["n_checkpoints"] = int(errors.size)
    say("fingerprint maps, leaving walks out")
    inferred = _fingerprint_errors(prepared, trajectories.signalslam, len(ap_index), folds)
    surveyed = _fingerprint_errors(prepared, None, len(ap_index), folds)
    result["fingerprint_p50_m"] = float(np.percentile(inferred, 50))
    result["fingerprint_p90_m"] = float(np.percentile(inferred, 90))
    result["fingerprint_surveyed_p50_m"] = float(np.percentile(surveyed, 50))
    result["fingerprint_surveyed_p90_m"] = float(np.percentile(surveyed, 90))
    result["seconds"] = time.perf_counter() - started
    return result, prepared, trajectories


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
    rss = np.full((int(keep.sum()), n_aps), np.nan)
    for r, entry in enumerate(e for e, k in zip(p.scans.rss, keep, strict=True) if k):
        rss[r, list(entry)] = list(entry.values())
    return p.scans.t_ms[keep], rss


def _fingerprint_errors(
    prepared: list[_Prepared], positions: list[np.ndarray] | None, n_aps: int, folds: int
) -> np.ndarray:
    """Weighted kNN (k = 7, weights 1/d over the union-fingerprint distance) of held-out walks' scans on a
    map of the other walks' scans placed by ``positions`` (None: surveyed positions)."""
    db_xy, db_rss, db_fold, q_xy, q_rss, q_fold = [], [], [], [], [], []
    for i, p in enumerate(prepared):
        wp = p.waypoints
        t, rss = _scan_matrix(p, n_aps, wp[0, 0], wp[-1, 0])
        truth = np.column_stack([np.interp(t, wp[:, 0], wp[:, k]) for k in (1, 2)])
        placed = truth if positions is None else position_at(p.walk.t_ms, positions[i], t)
        db_xy.append(placed)
        db_rss.append(rss)
        q_xy.append(truth)
        q_rss.append(rss)
        db_fold.append(np.full(t.size, i % folds))
        q_fold.append(np.full(t.size, i % folds))
    all_rss = np.vstack(db_rss)
    distance = fingerprint_matrix(all_rss)
    fold = np.concatenate(db_fold)
    xy = np.vstack(db_xy)
    truth = np.vstack(q_xy)
    distance[fold[:, None] == fold[None, :]] = np.inf  # a walk never localises against its own fold
    nearest = np.argsort(distance, axis=1, kind="stable")[:, :KNN]
    d = np.take_along_axis(distance, nearest, axis=1)
    w = np.where(np.isfinite(d), 1.0 / np.maximum(d, 1e-3), 0.0)
    ok = w.sum(axis=1) > 0
    estimate = np.einsum("qk,qkc->qc", w[ok], xy[nearest[ok]]) / w[ok].sum(axis=1, keepdims=True)
    errors: np.ndarray = np.linalg.norm(estimate - truth[ok], axis=1)
    return errors
