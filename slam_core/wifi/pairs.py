"""WiFi encounter features for every pair of scans at once, and how well each separates near from far pairs.

Scans are rows of a dense RSS matrix (scans x APs, NaN = not heard). Two features:

- ``eq3``: DynamicSLAM's Eq. 3 (``slam_core.wifi.similarity.eq3``); pairs with no common AP get +inf.
- ``fingerprint`` (ours): the union-fingerprint distance (``slam_core.wifi.similarity.union_rms``).

Pure numerics; the caller labels pairs (from surveyed positions) and picks thresholds.
"""

from __future__ import annotations

import numpy as np

from slam_core.wifi import similarity

FEATURES = ("eq3", "fingerprint")
STALE_AP_MS = 3_000
"""Scans re-report cached APs (on real phones 50-60 % of entries are older than 3 s): an entry whose
last-seen time is more than this before its scan is dropped before any WiFi feature."""


def fresh_mask(t_ms: int | np.ndarray, last_seen_ms: np.ndarray, stale_ms: int = STALE_AP_MS) -> np.ndarray:
    """Entries of a scan taken at ``t_ms`` (or of scans taken at each entry's ``t_ms``) that were heard in it,
    not re-reported from the phone's cache: last seen within ``stale_ms`` of the scan, or without a
    last-seen time (-1)."""
    fresh: np.ndarray = (last_seen_ms < 0) | (last_seen_ms >= t_ms - stale_ms)
    return fresh


def strongest_mask(rss: np.ndarray, n: int) -> np.ndarray:
    """(S, A) mask of each scan's ``n`` strongest heard APs (ties broken by AP order)."""
    filled = np.where(np.isnan(rss), -np.inf, rss)
    order = np.argsort(-filled, axis=1, kind="stable")[:, :n]
    mask = np.zeros(rss.shape, dtype=bool)
    np.put_along_axis(mask, order, True, axis=1)
    mask &= np.isfinite(filled)
    return mask


def dense_eq3_matrix(rss: np.ndarray, strongest_n: int = 5, min_common: int = 1) -> np.ndarray:
    """Eq. 3 between every pair of scans given as a dense (S, APs) RSS matrix: each scan's strongest
    ``strongest_n`` taken for ``similarity.eq3_matrix``; (S, S), +inf where fewer than ``min_common`` APs are
    common."""
    top = strongest_mask(rss, strongest_n)
    top_ap = np.full((rss.shape[0], strongest_n), -1, dtype=np.int64)
    top_rss = np.zeros((rss.shape[0], strongest_n))
    for i in range(rss.shape[0]):
        (heard,) = np.nonzero(top[i])
        top_ap[i, : heard.size] = heard
        top_rss[i, : heard.size] = rss[i, heard]
    result: np.ndarray = similarity.eq3_matrix(top_ap, top_rss, min_common)
    return result


def fingerprint_matrix(rss: np.ndarray, floor_dbm: float = -100.0) -> np.ndarray:
    """The union-fingerprint distance between every pair of scans, a missing AP counting as ``floor_dbm``;
    +inf for two empty scans."""
    heard = np.isfinite(rss).astype(np.float64)
    g = np.where(heard > 0, np.maximum(rss, floor_dbm) - floor_dbm, 0.0)
    squares = np.sum(g * g, axis=1)
    counts = heard.sum(axis=1)
    result: np.ndarray = similarity.union_rms_matrix(
        squares, squares, g @ g.T, counts, counts, heard @ heard.T
    )
    return result


def precision_recall(score: np.ndarray, positive: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thresholds (ascending) and the precision and recall of ``score <= threshold`` at each; a lower
    score means more similar. Pairs with an infinite score never pass."""
    score = np.asarray(score, dtype=float)
    positive = np.asarray(positive, dtype=bool)
    if score.shape != positive.shape:
        raise ValueError("score and positive must have the same shape")
    total = int(positive.sum())
    if total == 0:
        raise ValueError("no positive pairs: precision and recall are undefined")
    finite = np.isfinite(score)
    order = np.argsort(score[finite], kind="stable")
    s, p = score[finite][order], positive[finite][order]
    hits = np.cumsum(p)
    passed = np.arange(1, s.size + 1)
    last = np.r_[s[1:] != s[:-1], True][: s.size]  # one point per distinct threshold
    return s[last], (hits / passed)[last], (hits / total)[last]


def precision_at_recall(score: np.ndarray, positive: np.ndarray, recall: float) -> tuple[float, float]:
    """(precision, threshold) at the smallest threshold whose recall reaches ``recall``; (nan, inf) if no
    threshold does."""
    thresholds, precision, achieved = precision_recall(score, positive)
    index = np.searchsorted(achieved, recall)
    if index >= achieved.size:
        return float("nan"), float("inf")
    return float(precision[index]), float(thresholds[index])
