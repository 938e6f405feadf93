"""The joint crowd-map solve: analytic Jacobian against a numerical one, and a floor with a known optimum."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from slam_core.crowd.graph import CrowdGraph, CrowdGraphParams


def _rot(b: float, v: np.ndarray) -> np.ndarray:
    c, s = np.cos(b), np.sin(b)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def _synthetic(
    rng: np.random.Generator, noise: float, known: tuple[int, ...] = (0,)
) -> tuple[CrowdGraph, np.ndarray, dict[int, float]]:
    anchors = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 15.0], [0.0, 15.0], [10.0, 8.0]])
    graph = CrowdGraph(CrowdGraphParams(drift_fraction=0.01))
    for k in known:
        graph.set_known(k, anchors[k])
    biases = {}
    for u in range(8):
        bias, scale = rng.normal(0, 0.12), rng.normal(1, 0.08)
        biases[u] = bias
        start = anchors[0] + rng.normal(0, 0.3, 2)
        graph.add_user(u, start)
        position, displacement, walked = start, np.zeros(2), 0.0
        for a in rng.permutation(4) + 1:
            true_step = anchors[a] + rng.normal(0, noise, 2) - position
            # the phone reports the walk rotated by -bias and scaled by 1/scale
            displacement = displacement + _rot(-bias, true_step) / scale
            walked += float(np.linalg.norm(true_step))
            position = anchors[a]
            graph.add_detection(u, int(a), displacement, walked)
    return graph, anchors, biases


def test_analytic_jacobian_matches_a_numerical_one() -> None:
    graph, _, _ = _synthetic(np.random.default_rng(0), noise=0.3)
    problem = graph.problem({})
    assert problem is not None
    residuals, jacobian, x0 = problem.residuals, problem.jacobian, problem.x0
    x = x0 + np.random.default_rng(1).normal(0, 0.1, x0.size)
    numeric = np.array(
        [approx_fprime(x, lambda v, i=i: residuals(v)[i], 1e-7) for i in range(residuals(x).size)]
    )
    np.testing.assert_allclose(jacobian(x).toarray(), numeric, atol=1e-4)


def test_recovers_anchors_on_a_known_floor() -> None:
    """Two known anchors fix the floor's rotation and scale; every other anchor is recovered."""
    graph, anchors, _ = _synthetic(np.random.default_rng(2), noise=0.0, known=(0, 2))
    means, covs = graph.solve({a: anchors[a] + 3.0 for a in (1, 3, 4)})
    assert sorted(means) == [1, 3, 4]
    for a in (1, 3, 4):
        np.testing.assert_allclose(means[a], anchors[a], atol=0.3)
        assert np.all(np.linalg.eigvalsh(covs[a]) > 0)


def test_one_known_anchor_leaves_the_rotation_to_the_bias_priors() -> None:
    """With a single known anchor, a common heading bias rotates the whole map about it: only the prior
    (phones' biases average zero) pins it, so far anchors are off by about the users' mean bias."""
    graph, anchors, biases = _synthetic(np.random.default_rng(2), noise=0.0)
    means, _ = graph.solve({})
    angle = np.arctan2(means[1][1], means[1][0]) - np.arctan2(anchors[1][1], anchors[1][0])
    assert abs(angle) < 2.5 * abs(np.mean(list(biases.values()))) + 0.02
    assert np.linalg.norm(means[1]) == pytest.approx(20.0, rel=0.05)


def test_noisy_detections_still_land_near_the_truth() -> None:
    graph, anchors, _ = _synthetic(np.random.default_rng(3), noise=0.5)
    means, _ = graph.solve({})
    errors = [np.linalg.norm(means[a] - anchors[a]) for a in range(1, 5)]
    assert max(errors) < 1.0


def test_nothing_to_solve_without_detections() -> None:
    graph = CrowdGraph()
    graph.add_user(0, np.zeros(2))
    assert graph.solve({}) == ({}, {})
    assert graph.problem({}) is None


def _two_floors(rng: np.random.Generator) -> tuple[CrowdGraph, CrowdGraph, CrowdGraph]:
    """One graph holding two crowds that share no unknown anchor (two floors: anchors 1-4 and 11-14, the
    known anchor 0 seen by both), and each crowd's graph alone."""
    both, lower, upper = CrowdGraph(), CrowdGraph(), CrowdGraph()
    for graph in (both, lower, upper):
        graph.set_known(0, np.zeros(2))
    for u in range(10):
        offset = 0 if u < 5 else 10
        start = rng.normal(0, 0.3, 2)
        alone = lower if u < 5 else upper
        for graph in (both, alone):
            graph.add_user(u, start)
        displacement, walked = np.zeros(2), 0.0
        for a in [0, *(rng.permutation(4) + 1 + offset)]:
            step = rng.normal(0, 8.0, 2)
            displacement, walked = displacement + step, walked + float(np.linalg.norm(step))
            for graph in (both, alone):
                graph.add_detection(u, int(a), displacement, walked)
    return both, lower, upper


def test_crowds_that_share_no_anchor_are_solved_apart_as_they_would_be_alone() -> None:
    """The parts of a graph (users joined by the unknown anchors they detected; a known anchor joins none) are
    solved one by one: each part's anchors equal its crowd's solve alone, and a solve touching one part's
    anchors leaves the other's unsolved."""
    both, lower, upper = _two_floors(np.random.default_rng(4))
    assert both.components() == [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9]]
    means, covs = both.solve({})
    alone = {**lower.solve({})[0], **upper.solve({})[0]}
    assert sorted(means) == sorted(alone) == [1, 2, 3, 4, 11, 12, 13, 14]
    for a, mean in alone.items():
        np.testing.assert_allclose(means[a], mean, atol=1e-9)
        np.testing.assert_allclose(covs[a], covs[a].T)
        assert np.all(np.linalg.eigvalsh(covs[a]) > 0)
    touched, _ = both.solve({}, touching={12})
    assert sorted(touched) == [11, 12, 13, 14]
    assert both.solve({}, touching={0}) == ({}, {})  # a known anchor is in no part
    # a user who walks from one crowd's anchors to the other's joins them into one part
    both.add_detection(4, 13, np.array([1.0, 1.0]), 100.0)
    assert both.components() == [[0, 1, 2, 3, 4, 5, 6, 7, 8, 9]]
