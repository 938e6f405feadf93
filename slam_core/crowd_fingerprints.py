"""A WiFi fingerprint map learned by the crowd while it is tracked, and WiFi localisation on it.

Beyond DynamicSLAM (SignalSLAM's fingerprint localisation, Section IV, used live): every fresh WiFi scan of a
tracked user whose estimate is confident joins the map at that estimate; a later scan of another user is
localised by weighted kNN (weights 1/d) over the union-fingerprint distance (``slam_core.wifi_pairs``: RMS dB
over the union of both scans' APs, a missing AP at ``floor_dbm``), and the result becomes a robust position
observation of that user (``DynamicSlam.observe_position_robust``). A user's own scans are never its
references: they would only confirm its own estimate.

Memory is bounded (``max_references``, oldest dropped first); a query costs O(references x APs of the
query), not O(references x all APs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FingerprintParams:
    enabled: bool = False
    k: int = 7
    """Neighbours of the weighted kNN (the fingerprint localisation's k)."""
    sigma_m: float = 15.0
    """The observation's sigma. On msindoor site1 F1 (warm replay) the fixes were off by 6.7 / 11 / 18 m
    (p50 / p75 / p90; a map at surveyed positions reaches 4.6 m p50): a core sigma of ~6 m, widened for
    consecutive scans of one walk, which err alike (the map's error is a place's, not a scan's). Measured:
    sigma 10 m 2.55 / 5.21, 15 m 2.54 / 5.13 (p50 / p90 of the replay; 2.62 / 5.31 without fixes)."""
    outlier_probability: float = 0.3
    """Share of fixes that are wrong (msindoor: the kNN's p90 is about twice its p50, with a long tail)."""
    outlier_radius_m: float = 50.0
    """A wrong fix lands anywhere within this radius: the outlier term's density is 1 / (pi r^2)."""
    max_reference_std_m: float = 3.0
    """A scan joins the map only when its user's estimate is this certain (the larger axis' sigma)."""
    max_spread_m: float = 12.0
    """A scan whose k neighbours lie further apart than this (weighted RMS about their mean) is not
    localised: on msindoor site1 F1 such fixes were off by 11 m p50 (the others by 4.9-7.1 m)."""
    min_references: int = 50
    """No fix before the map holds this many scans of other users."""
    max_references: int = 20_000
    min_aps: int = 3
    """A scan with fewer fresh APs is neither stored nor localised."""
    floor_dbm: float = -100.0

    def __post_init__(self) -> None:
        if self.k < 1 or self.min_references < self.k or self.max_references < self.min_references:
            raise ValueError("fingerprint map needs 1 <= k <= min_references <= max_references")
        if min(self.sigma_m, self.outlier_radius_m, self.max_reference_std_m, self.max_spread_m) <= 0:
            raise ValueError("fingerprint sigmas and radius must be positive")
        if not 0.0 <= self.outlier_probability < 1.0:
            raise ValueError("outlier_probability must be in [0, 1)")
        if self.min_aps < 1:
            raise ValueError("min_aps must be >= 1")


class CrowdFingerprints:
    """Placed scans in dense arrays over an interned BSSID index; rows are a ring of ``max_references``."""

    def __init__(self, params: FingerprintParams) -> None:
        self.params = params
        self._columns: dict[str, int] = {}
        n = min(64, params.max_references)
        self._gain = np.zeros((n, 16), dtype=np.float32)  # RSS above the floor, 0 where not heard
        self._heard = np.zeros((n, 16), dtype=np.float32)
        self._norm = np.zeros(n)  # sum of squared gains per row
        self._count = np.zeros(n)  # APs heard per row
        self._xy = np.zeros((n, 2))
        self._owner = np.full(n, -1, dtype=np.int64)
        self._size = 0
        self._next = 0

    def __len__(self) -> int:
        return self._size

    def _row(self, bssids: list[str], rss: np.ndarray, intern: bool) -> tuple[np.ndarray, np.ndarray]:
        """Columns and gains of a scan's finite entries (a BSSID listed twice counts once, strongest)."""
        row: dict[int, float] = {}
        for b, r in zip(bssids, np.asarray(rss, dtype=float), strict=True):
            c = self._columns.get(b)
            if c is None and intern:
                c = self._columns[b] = len(self._columns)
            if c is not None and np.isfinite(r):
                gain = max(float(r), self.params.floor_dbm) - self.params.floor_dbm
                row[c] = max(gain, row.get(c, 0.0))
        return np.fromiter(row.keys(), np.int64, len(row)), np.fromiter(row.values(), np.float32, len(row))

    def add(self, owner: int, xy: np.ndarray, bssids: list[str], rss: np.ndarray) -> bool:
        """Store one scan (fresh entries only) at ``xy``; False when it has too few APs."""
        if len(bssids) < self.params.min_aps:
            return False
        cols, gains = self._row(bssids, rss, intern=True)
        if cols.size < self.params.min_aps:
            return False
        self._grow(len(self._columns))
        row = self._next
        self._gain[row] = 0.0
        self._heard[row] = 0.0
        self._gain[row, cols] = gains
        self._heard[row, cols] = 1.0
        self._norm[row] = float(gains.astype(float) @ gains.astype(float))
        self._count[row] = cols.size
        self._xy[row] = xy
        self._owner[row] = owner
        self._next = (row + 1) % self.params.max_references
        self._size = min(self._size + 1, self.params.max_references)
        return True

    def _grow(self, n_columns: int) -> None:
        rows, cols = self._gain.shape
        # the ring wraps only at max_references, so rows are short exactly when the next one is past the end
        new_rows = min(2 * rows, self.params.max_references) if self._next >= rows else rows
        new_cols = max(2 * cols, n_columns) if n_columns > cols else cols
        if (new_rows, new_cols) == (rows, cols):
            return
        for name in ("_gain", "_heard"):
            grown = np.zeros((new_rows, new_cols), dtype=np.float32)
            grown[:rows, :cols] = getattr(self, name)
            setattr(self, name, grown)
        for name, fill in (("_norm", 0.0), ("_count", 0.0), ("_owner", -1)):
            old = getattr(self, name)
            longer = np.full(new_rows, fill, dtype=old.dtype)
            longer[:rows] = old
            setattr(self, name, longer)
        xy = np.zeros((new_rows, 2))
        xy[:rows] = self._xy
        self._xy = xy

    def locate(self, owner: int, bssids: list[str], rss: np.ndarray) -> np.ndarray | None:
        """Weighted-kNN position of a scan over the other users' stored scans, or None when the map cannot
        say (too few references, too few APs in common)."""
        p = self.params
        if len(bssids) < p.min_aps:
            return None
        cols, gains = self._row(bssids, rss, intern=False)
        n = self._size
        others = self._owner[:n] != owner
        if cols.size < p.min_aps or int(others.sum()) < p.min_references:
            return None
        query = gains.astype(float)
        # Union RMS: |g_ref|^2 + |g_q|^2 - 2 g_ref . g_q over n_ref + n_q - shared APs (slam_core.wifi_pairs)
        dot = self._gain[:n, cols].astype(float) @ query
        shared = self._heard[:n, cols].sum(axis=1, dtype=float)
        union = self._count[:n] + cols.size - shared
        squared = self._norm[:n] + float(query @ query) - 2.0 * dot
        distance = np.sqrt(np.maximum(squared, 0.0) / np.maximum(union, 1.0))
        distance = np.where(others & (shared > 0), distance, np.inf)
        k = min(p.k, n)
        nearest = np.argpartition(distance, k - 1)[:k]
        d = distance[nearest]
        if not np.all(np.isfinite(d)):
            return None
        w = 1.0 / np.maximum(d, 1e-3)
        w /= w.sum()
        estimate: np.ndarray = w @ self._xy[nearest]
        spread = float(np.sqrt(w @ np.sum((self._xy[nearest] - estimate) ** 2, axis=1)))
        if spread > p.max_spread_m:  # the neighbours disagree: the map does not know this place
            return None
        return estimate
