"""All-pairs WiFi features against direct per-pair computations, and precision/recall against counting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.encounters import WifiEq3Params, wifi_eq3_similarity
from slam_core.wifi_pairs import (
    eq3_matrix,
    fingerprint_matrix,
    precision_at_recall,
    precision_recall,
    strongest_mask,
)


def _scans(n: int = 30, aps: int = 25, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rss = rng.uniform(-95.0, -40.0, (n, aps)).round()  # integer dBm: ties happen, as on phones
    rss[rng.random((n, aps)) < 0.6] = np.nan
    rss[3] = np.nan  # an empty scan
    return rss


@pytest.mark.parametrize("min_common", [1, 2])
def test_eq3_matrix_matches_the_per_pair_definition(min_common: int) -> None:
    rss = _scans()
    params = WifiEq3Params(min_common=min_common)
    ours = eq3_matrix(rss, params.strongest_n, params.min_common)
    for i in range(rss.shape[0]):
        for j in range(rss.shape[0]):
            expected, _ = wifi_eq3_similarity(rss[i], rss[j], params)
            if math.isinf(expected):
                assert math.isinf(ours[i, j])
            else:
                assert ours[i, j] == pytest.approx(expected, abs=1e-9)


def test_fingerprint_matrix_matches_a_direct_computation() -> None:
    rss = _scans(seed=1)
    ours = fingerprint_matrix(rss, floor_dbm=-100.0)
    for i in range(rss.shape[0]):
        for j in range(rss.shape[0]):
            union = np.isfinite(rss[i]) | np.isfinite(rss[j])
            if not union.any():
                assert math.isinf(ours[i, j])
                continue
            a = np.where(np.isfinite(rss[i]), rss[i], -100.0)[union]
            b = np.where(np.isfinite(rss[j]), rss[j], -100.0)[union]
            assert ours[i, j] == pytest.approx(float(np.sqrt(np.mean((a - b) ** 2))), abs=1e-6)
    assert np.allclose(np.diag(ours)[np.isfinite(np.diag(ours))], 0.0, atol=1e-6)


def test_strongest_mask_picks_the_strongest_heard_aps() -> None:
    rss = np.array([[-50.0, np.nan, -70.0, -40.0], [np.nan, np.nan, -60.0, np.nan]])
    np.testing.assert_array_equal(
        strongest_mask(rss, 2), [[True, False, False, True], [False, False, True, False]]
    )


def test_precision_recall_by_counting() -> None:
    rng = np.random.default_rng(2)
    score = rng.normal(size=500)
    score[:20] = np.inf
    positive = rng.random(500) < 0.3
    thresholds, precision, recall = precision_recall(score, positive)
    assert np.all(np.diff(thresholds) > 0)
    assert np.all(np.diff(recall) >= 0)
    for k in (0, 50, len(thresholds) - 1):
        passed = score <= thresholds[k]
        assert precision[k] == pytest.approx(positive[passed].mean())
        assert recall[k] == pytest.approx(positive[passed].sum() / positive.sum())
    p, t = precision_at_recall(score, positive, 0.5)
    assert positive[score <= t].sum() >= 0.5 * positive.sum()
    assert p == pytest.approx(positive[score <= t].mean())
    all_inf = np.full(5, np.inf)
    assert math.isnan(precision_at_recall(all_inf, np.array([True] * 5), 0.5)[0])


def test_precision_recall_errors() -> None:
    with pytest.raises(ValueError, match="no positive pairs"):
        precision_recall(np.zeros(3), np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="same shape"):
        precision_recall(np.zeros(3), np.zeros(2, dtype=bool))
