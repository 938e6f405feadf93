"""Signal-similarity kernels, SignalSLAM Section II-D: k(S_i, S_j) = exp(-alpha D).

- WiFi / Bluetooth: D is the symmetrised Kullback-Leibler divergence KL(p||q) + KL(q||p) between the
  multinomials of access-point visibility of two time windows (how often each AP was heard in the window's
  scans), smoothed with ``epsilon`` so an AP heard in one window only gives a finite divergence.
- LTE RSRP, magnetic magnitude: D is the squared Euclidean distance (Gaussian kernel). For LTE the vectors
  are over cells, and two windows rarely hear the same set: D is the mean squared RSRP difference over the
  union of both windows' cells, a cell one window did not hear counting at ``floor_dbm`` (as the WiFi
  union fingerprint does), so windows served by different cells are far apart.
Kernels of several modalities over the same windows multiply element-wise.
"""

from __future__ import annotations

import numpy as np

from slam_core.wifi.pairs import fingerprint_matrix


def visibility_multinomials(counts: np.ndarray, epsilon: float = 1e-3) -> np.ndarray:
    """(W, A) AP sighting counts per window -> rows of smoothed visibility probabilities."""
    counts = np.asarray(counts, dtype=float)
    if counts.ndim != 2 or np.any(counts < 0):
        raise ValueError("counts must be a (windows, APs) array of non-negative counts")
    smoothed = counts + epsilon
    probabilities: np.ndarray = smoothed / smoothed.sum(axis=1, keepdims=True)
    return probabilities


def symmetric_kl(p: np.ndarray, q: np.ndarray | None = None) -> np.ndarray:
    """(W1, W2) matrix of KL(p_i||q_j) + KL(q_j||p_i) = sum_a (p_a - q_a)(log p_a - log q_a)."""
    q = p if q is None else q
    lp, lq = np.log(p), np.log(q)
    # sum (p - q)(lp - lq) = sum p lp + sum q lq - p.lq - q.lp
    self_p = np.sum(p * lp, axis=1)
    self_q = np.sum(q * lq, axis=1)
    divergence: np.ndarray = np.maximum(self_p[:, None] + self_q[None, :] - p @ lq.T - lp @ q.T, 0.0)
    return divergence


def kl_kernel(p: np.ndarray, q: np.ndarray | None = None, alpha: float = 1.0) -> np.ndarray:
    kernel: np.ndarray = np.exp(-alpha * symmetric_kl(p, q))
    return kernel


def _rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x.reshape(-1, 1) if x.ndim == 1 else x


def gaussian_kernel(a: np.ndarray, b: np.ndarray | None = None, alpha: float = 1.0) -> np.ndarray:
    """exp(-alpha ||a_i - b_j||^2) for rows of feature vectors (a 1-D array is one feature per window)."""
    a = _rows(a)
    b = a if b is None else _rows(b)
    squared = np.sum(a * a, axis=1)[:, None] + np.sum(b * b, axis=1)[None, :] - 2.0 * a @ b.T
    kernel: np.ndarray = np.exp(-alpha * np.maximum(squared, 0.0))
    return kernel


def union_gaussian_kernel(rows: np.ndarray, alpha: float, floor_dbm: float) -> np.ndarray:
    """(W, W) exp(-alpha D), D the mean squared difference over the union of both rows' finite entries, a
    missing entry at ``floor_dbm``. Pairs where neither row has an entry get 1 (no evidence either way)."""
    rows = np.asarray(rows, dtype=float)
    if rows.ndim != 2:
        raise ValueError("rows must be a (windows, cells) array, NaN where a cell was not heard")
    rms = fingerprint_matrix(rows, floor_dbm)  # the union RMS; +inf where neither row has an entry
    kernel: np.ndarray = np.where(np.isfinite(rms), np.exp(-alpha * np.square(rms)), 1.0)
    return kernel
