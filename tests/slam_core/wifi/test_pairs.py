"""The pair features' helpers: strongest APs, freshness, and precision/recall against counting (the features
themselves are checked against their references in ``test_similarity``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.wifi.pairs import (
    precision_at_recall,
    precision_recall,
    strongest_mask,
)


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
