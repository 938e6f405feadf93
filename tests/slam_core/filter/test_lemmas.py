"""The paper's Lemma 1 and Lemma 2 (Section 4.3), checked by Monte Carlo on the engine itself."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from slam_core.filter.dynamic_slam import CrowdMap, DynamicSlam
from slam_core.filter.params import FilterParams, MotionParams

PARAMS = FilterParams(n_particles=75, motion=MotionParams(model="paper"))


def _drifted_user(
    engine: DynamicSlam, rng: np.random.Generator, truth: np.ndarray, error_sigma: float
) -> int:
    start = truth + rng.normal(0.0, error_sigma, 2)
    return engine.add_user(float(start[0]), float(start[1]), position_sigma=error_sigma)


def test_lemma2_a_known_anchor_shrinks_the_error_in_expectation() -> None:
    """A user with a position error who detects an operator-known anchor ends up closer to the truth."""
    rng = np.random.default_rng(0)
    truth = np.array([10.0, 5.0])
    crowd = CrowdMap(
        truth[None, :], np.array([[1e-4, 0.0, 1e-4]]), np.array([0]), np.array([True]), np.array([0])
    )
    before, after = [], []
    for trial in range(60):
        engine = DynamicSlam(PARAMS, seed=trial)
        u = _drifted_user(engine, rng, truth, 2.0)
        engine.state.map_mu[u, :, 0] = truth
        engine.state.map_cov[u, :, 0] = (1e-4, 0.0, 1e-4)
        engine.state.map_known[u, :, 0] = True
        engine.state.map_n[u] = 1
        before.append(np.linalg.norm(engine.summaries(np.array([u]))[0, :2] - truth))
        engine.observe_building_anchors(np.array([u]), np.array([0]))
        after.append(np.linalg.norm(engine.summaries(np.array([u]))[0, :2] - truth))
    assert crowd.mean.shape == (1, 2)
    assert np.mean(after) < 0.6 * np.mean(before), (np.mean(before), np.mean(after))


def test_lemma1_the_less_accurate_user_improves_and_the_better_one_is_not_dragged_far() -> None:
    rng = np.random.default_rng(1)
    params = replace(PARAMS, human=replace(PARAMS.human, gate_sigma=10.0, outlier_probability=0.01))
    gain_poor, loss_good = [], []
    for trial in range(60):
        engine = DynamicSlam(params, seed=trial)
        truth_a = np.array([0.0, 0.0])
        truth_b = np.array([3.0, 0.0])
        good = _drifted_user(engine, rng, truth_a, 0.3)
        poor = _drifted_user(engine, rng, truth_b, 3.0)
        s0 = engine.summaries(np.array([good, poor]))
        e_good0, e_poor0 = np.linalg.norm(s0[0, :2] - truth_a), np.linalg.norm(s0[1, :2] - truth_b)
        z = np.linalg.norm(truth_a - truth_b) + rng.normal(0, 0.3)
        engine.observe_encounters(np.array([good]), np.array([poor]), np.array([z]), np.array([0.09]))
        s1 = engine.summaries(np.array([good, poor]))
        gain_poor.append(e_poor0 - np.linalg.norm(s1[1, :2] - truth_b))
        loss_good.append(np.linalg.norm(s1[0, :2] - truth_a) - e_good0)
    assert np.mean(gain_poor) > 0.2, np.mean(gain_poor)  # the poor user's error shrinks in expectation
    assert np.mean(loss_good) < 0.3, np.mean(loss_good)  # the good user's error grows little, if at all
