"""Each compiled kernel against the plain-NumPy textbook filter on identical inputs and random streams."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from slam_core.filter import reference
from slam_core.filter.dynamic_slam import CrowdMap, DynamicSlam
from slam_core.filter.params import FilterParams, HumanAnchorParams, MotionParams, ResamplingParams
from tests.slam_core.filter.helpers import assert_matches, to_reference

SMALL = FilterParams(n_particles=12)


def _walk(
    engine: DynamicSlam, u: int, ref: reference.ReferenceUser, params: FilterParams, n: int, turn: float
) -> None:
    rng = np.random.default_rng(7)
    heading = 0.3
    for _ in range(n):
        heading += turn + rng.normal(0, 0.05)
        length = 0.7 + rng.normal(0, 0.03)
        engine.step(np.array([u]), np.array([0, 1]), np.array([length]), np.array([heading]))
        reference.motion(ref, length, heading, params)


@pytest.mark.parametrize("model", ["paper", "bias-scale"])
def test_motion_matches_reference(model: str) -> None:
    params = replace(SMALL, motion=MotionParams(model=model))
    engine = DynamicSlam(params, seed=3)
    u = engine.add_user(1.0, 2.0, heading=0.5)
    ref = to_reference(engine, u)
    _walk(engine, u, ref, params, 25, 0.02)
    assert_matches(engine, u, ref)
    np.testing.assert_allclose(
        engine.state.ctrl_cov[u], [ref.ctrl_cov[0, 0], ref.ctrl_cov[0, 1], ref.ctrl_cov[1, 1]]
    )


def test_several_steps_in_one_call_equal_one_call_per_step() -> None:
    a = DynamicSlam(SMALL, seed=1)
    b = DynamicSlam(SMALL, seed=1)
    ua, ub = a.add_user(0, 0), b.add_user(0, 0)
    lengths = np.array([0.7, 0.65, 0.72])
    headings = np.array([0.1, 0.2, 0.15])
    a.step(np.array([ua]), np.array([0, 3]), lengths, headings)
    for k in range(3):
        b.step(np.array([ub]), np.array([0, 1]), lengths[k : k + 1], headings[k : k + 1])
    np.testing.assert_array_equal(a.state.x, b.state.x)
    np.testing.assert_array_equal(a.state.y, b.state.y)


@pytest.mark.parametrize("sampling", ["one-shot", "iterative"])
def test_human_anchor_matches_reference(sampling: str) -> None:
    params = replace(
        SMALL, human=HumanAnchorParams(sampling=sampling), resampling=ResamplingParams(ess_threshold=1e-9)
    )
    engine = DynamicSlam(params, seed=5)
    u = engine.add_user(0.0, 0.0, position_sigma=2.0)
    peer = engine.add_user(3.0, 1.0)
    ref = to_reference(engine, u)
    _walk(engine, u, ref, params, 10, 0.0)
    peer_summary = engine.summaries(np.array([peer]))[0]
    peer_mean, peer_cov = peer_summary[0:2], peer_summary[2:5]
    engine._human_update(
        np.array([u]), peer_mean[None, :], peer_cov[None, :], np.array([4.0]), np.array([2.5])
    )
    reference.human_anchor(
        ref, peer_mean, np.array([[peer_cov[0], peer_cov[1]], [peer_cov[1], peer_cov[2]]]), 4.0, 2.5, params
    )
    assert_matches(engine, u, ref)


def test_building_anchor_matches_reference_including_new_anchors_and_known_ones() -> None:
    params = replace(SMALL, resampling=ResamplingParams(ess_threshold=1e-9))
    crowd = CrowdMap(
        mean=np.array([[7.0, 2.0], [20.0, 0.0]]),
        cov=np.array([[0.5, 0.1, 0.4], [1.0, 0.0, 1.0]]),
        type=np.array([0, 2]),
        known=np.array([False, True]),
        crowd_id=np.array([10, 11]),
    )
    engine = DynamicSlam(params, seed=11)
    u = engine.add_user(0.0, 0.0, position_sigma=1.0, crowd_map=crowd)
    ref = to_reference(engine, u)
    for k, detected in enumerate([0, 3, 2]):  # existing anchor, a new one, the known one
        _walk(engine, u, ref, params, 10 if k == 0 else 5 + 10 * k, 0.0)
        engine.observe_building_anchors(np.array([u]), np.array([detected]))
        reference.building_anchor(ref, detected, params)
        assert_matches(engine, u, ref)


@pytest.mark.parametrize("scheme", ["systematic", "stratified", "residual", "multinomial"])
def test_resampling_matches_reference(scheme: str) -> None:
    params = replace(SMALL, resampling=ResamplingParams(scheme=scheme, ess_threshold=1.0))
    engine = DynamicSlam(params, seed=2)
    u = engine.add_user(0.0, 0.0, position_sigma=3.0)
    rng = np.random.default_rng(0)
    logw = rng.normal(0, 1.5, params.n_particles)
    logw -= np.log(np.exp(logw).sum())
    engine.state.logw[u] = logw
    ref = to_reference(engine, u)
    engine._resample(np.array([u]))
    assert reference.resample(ref, params)
    assert_matches(engine, u, ref)
    assert engine.state.n_resamples[u] == 1


def test_summary_matches_reference() -> None:
    engine = DynamicSlam(SMALL, seed=4)
    u = engine.add_user(2.0, -1.0, position_sigma=1.5)
    logw = np.random.default_rng(1).normal(0, 1, SMALL.n_particles)
    engine.state.logw[u] = logw - np.log(np.exp(logw).sum())
    ref = to_reference(engine, u)
    np.testing.assert_allclose(engine.summaries(np.array([u]))[0], reference.summary(ref), atol=1e-12)


def test_reference_rng_is_the_kernel_rng() -> None:
    engine = DynamicSlam(SMALL, seed=9)
    u = engine.add_user(0.0, 0.0)
    ref_rng = reference.CounterRng(int(engine.state.rng_key[u]), 0)
    ref_x = [ref_rng.normal() * 0.5 for _ in range(1)]
    assert math.isclose(engine.state.x[u, 0], ref_x[0], abs_tol=1e-12)
