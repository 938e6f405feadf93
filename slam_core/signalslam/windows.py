"""Signal windows (SignalSLAM Section II-E: 10 s windows every second) and scan rows, from sparse scans.

A scan is a dict of AP column -> RSS (dBm) over a building's or floor's AP index.
"""

from __future__ import annotations

import numpy as np

WINDOW_MS = 10_000
WINDOW_STEP_MS = 1_000


def window_counts(
    centres: np.ndarray,
    scan_t: np.ndarray,
    scans: list[dict[int, float]],
    n_aps: int,
    window_ms: int = WINDOW_MS,
) -> np.ndarray:
    """(W, n_aps) how many scans within +- window_ms / 2 of each centre heard each AP."""
    counts = np.zeros((centres.size, n_aps))
    for t, entry in zip(scan_t, scans, strict=True):
        rows = np.flatnonzero(np.abs(centres - t) <= window_ms // 2)
        cols = np.fromiter(entry.keys(), dtype=np.int64, count=len(entry))
        counts[np.ix_(rows, cols)] += 1.0
    return counts


def window_means(
    centres: np.ndarray,
    t_ms: np.ndarray,
    readings: list[dict[int, float]],
    n_columns: int,
    window_ms: int = WINDOW_MS,
) -> np.ndarray:
    """(W, n_columns) mean of each column's readings within +- window_ms / 2 of each centre (LTE RSRP per
    cell); NaN where a window has none."""
    sums = np.zeros((centres.size, n_columns))
    counts = np.zeros((centres.size, n_columns))
    for t, entry in zip(t_ms, readings, strict=True):
        rows = np.flatnonzero(np.abs(centres - t) <= window_ms // 2)
        cols = np.fromiter(entry.keys(), dtype=np.int64, count=len(entry))
        sums[np.ix_(rows, cols)] += np.fromiter(entry.values(), dtype=float, count=len(entry))
        counts[np.ix_(rows, cols)] += 1.0
    means: np.ndarray = np.where(counts > 0, sums / np.maximum(counts, 1.0), np.nan)
    return means


def window_sightings(
    centres: np.ndarray, t_ms: np.ndarray, columns: np.ndarray, n_columns: int, window_ms: int = WINDOW_MS
) -> np.ndarray:
    """(W, n_columns) how many sightings of each column (a Bluetooth beacon) fall within +- window_ms / 2
    of each centre."""
    counts = np.zeros((centres.size, n_columns))
    half = window_ms // 2
    for t, col in zip(t_ms, columns, strict=True):
        counts[np.abs(centres - t) <= half, col] += 1.0
    return counts


def window_mean_series(
    centres: np.ndarray, t_ms: np.ndarray, values: np.ndarray, window_ms: int = WINDOW_MS
) -> np.ndarray:
    """(W,) mean of a time-ordered series (the magnetic magnitude) within +- window_ms / 2 of each centre;
    NaN where a window has no sample."""
    half = window_ms // 2
    if t_ms.size == 0:
        return np.full(centres.size, np.nan)
    lo = np.searchsorted(t_ms, centres - half)
    hi = np.searchsorted(t_ms, centres + half, side="right")
    sums = np.concatenate([[0.0], np.cumsum(values)])
    n = hi - lo
    means: np.ndarray = np.where(n > 0, (sums[hi] - sums[lo]) / np.maximum(n, 1), np.nan)
    return means


def rss_matrix(scans: list[dict[int, float]], n_aps: int) -> np.ndarray:
    """(S, n_aps) RSS rows, NaN where a scan did not hear an AP."""
    rss = np.full((len(scans), n_aps), np.nan)
    for r, entry in enumerate(scans):
        rss[r, list(entry)] = list(entry.values())
    return rss
