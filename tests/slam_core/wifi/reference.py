"""Plain NumPy and Python references of the WiFi similarity measures: the oracles of
``slam_core.wifi.similarity``'s kernels and of every caller of them."""

from __future__ import annotations

import math

import numpy as np


def strongest(rss: np.ndarray, n: int) -> np.ndarray:
    heard = np.flatnonzero(~np.isnan(rss))
    return heard[np.argsort(-rss[heard], kind="stable")[:n]]


def eq3_dense(rss_a: np.ndarray, rss_b: np.ndarray, n: int = 5, min_common: int = 1) -> tuple[float, int]:
    """DynamicSLAM Eq. 3 on dense RSS vectors (NaN = not heard): ||U1 - U2|| / n over the common APs of both
    scans' strongest ``n``."""
    common = np.intersect1d(strongest(rss_a, n), strongest(rss_b, n))
    if common.size < max(min_common, 1):
        return math.inf, int(common.size)
    return float(np.linalg.norm(rss_a[common] - rss_b[common]) / common.size), int(common.size)


def eq3_sparse(top_a: dict[int, float], top_b: dict[int, float]) -> tuple[float, int]:
    """Eq. 3 over two strongest-N tables {AP: RSS}: (||U1 - U2|| / n, n); (inf, 0) if none is common."""
    common = top_a.keys() & top_b.keys()
    if not common:
        return math.inf, 0
    return math.sqrt(sum((top_a[k] - top_b[k]) ** 2 for k in common)) / len(common), len(common)


def union_rms_sparse(a: dict[int, float], b: dict[int, float], floor_dbm: float) -> float:
    """RMS dB difference over the union of two scans' APs {AP: RSS}, a missing AP counting as the floor."""
    keys = a.keys() | b.keys()
    if not keys:
        return math.inf
    total = sum(
        (max(a.get(k, floor_dbm), floor_dbm) - max(b.get(k, floor_dbm), floor_dbm)) ** 2 for k in keys
    )
    return math.sqrt(total / len(keys))


def eq3_matrix_products(rss: np.ndarray, n: int = 5, min_common: int = 1) -> np.ndarray:
    """Eq. 3 between every pair of dense scans with three matrix products."""
    top = np.zeros(rss.shape)
    for i in range(rss.shape[0]):
        top[i, strongest(rss[i], n)] = 1.0
    x = np.where(top > 0, rss, 0.0)
    common = top @ top.T
    squared = (x * x) @ top.T + top @ (x * x).T - 2.0 * (x @ x.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        sim = np.sqrt(np.maximum(squared, 0.0)) / common
    sim[common < max(min_common, 1)] = np.inf
    return sim


def union_rms_dense(rss_a: np.ndarray, rss_b: np.ndarray, floor_dbm: float) -> float:
    union = np.isfinite(rss_a) | np.isfinite(rss_b)
    if not union.any():
        return math.inf
    a = np.maximum(np.where(np.isfinite(rss_a), rss_a, floor_dbm), floor_dbm)[union]
    b = np.maximum(np.where(np.isfinite(rss_b), rss_b, floor_dbm), floor_dbm)[union]
    return float(np.sqrt(np.mean((a - b) ** 2)))
