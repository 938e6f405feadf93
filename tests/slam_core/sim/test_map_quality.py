"""The learned map's scores against hand-computed ones."""

from __future__ import annotations

import numpy as np
import pytest

from slam_core.sim.map_quality import map_quality

TRUE_XY = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])


def test_scores_a_map_with_a_duplicate_and_a_wrong_association() -> None:
    # crowd 0 is known (true 0); crowd 1 learned true 1 (three detections, one of them really of true 2);
    # crowd 2 and crowd 3 both learned true 2 (a duplicate)
    ids = np.array([0, 0, 1, 1, 1, 2, 2, 3])
    truth = np.array([0, 0, 1, 1, 2, 2, 2, 2])
    means = {
        0: np.array([0.0, 0.0]),
        1: np.array([10.0, 3.0]),
        2: np.array([1.0, 10.0]),
        3: np.array([0.0, 8.0]),
    }
    out = map_quality(ids, truth, means, {0}, TRUE_XY)
    assert out["map_anchors_learned"] == 3  # the known anchor is not scored for position
    assert out["map_error_median_m"] == pytest.approx(2.0)  # errors 3, 1 and 2 m
    assert out["map_error_p90_m"] == pytest.approx(np.percentile([3.0, 1.0, 2.0], 90))
    assert out["map_duplicate_anchors"] == 1
    assert out["map_misassociated_fraction"] == pytest.approx(1 / 8)


def test_a_removed_anchor_is_not_scored_for_position() -> None:
    out = map_quality(np.array([5, 6]), np.array([1, 2]), {6: np.array([0.0, 9.0])}, set(), TRUE_XY)
    assert out["map_anchors_learned"] == 1
    assert out["map_error_median_m"] == pytest.approx(1.0)
    assert out["map_duplicate_anchors"] == 0
    assert out["map_misassociated_fraction"] == 0.0


def test_no_detections_give_no_errors() -> None:
    out = map_quality(np.zeros(0, np.int64), np.zeros(0, np.int64), {}, set(), TRUE_XY)
    assert out["map_anchors_learned"] == 0
    assert out["map_error_median_m"] is None
    assert out["map_error_p90_m"] is None
    assert out["map_misassociated_fraction"] == 0.0


def test_inputs_that_do_not_fit_are_refused() -> None:
    with pytest.raises(ValueError, match="equally long"):
        map_quality(np.array([0, 1]), np.array([0]), {}, set(), TRUE_XY)
    with pytest.raises(ValueError, match="not in true_anchor_xy"):
        map_quality(np.array([0]), np.array([3]), {}, set(), TRUE_XY)
