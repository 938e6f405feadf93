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


def rss_matrix(scans: list[dict[int, float]], n_aps: int) -> np.ndarray:
    """(S, n_aps) RSS rows, NaN where a scan did not hear an AP."""
    rss = np.full((len(scans), n_aps), np.nan)
    for r, entry in enumerate(scans):
        rss[r, list(entry)] = list(entry.values())
    return rss
