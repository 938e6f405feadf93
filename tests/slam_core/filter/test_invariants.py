"""Filter invariants under random operation sequences, error paths, and determinism across thread counts."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slam_core.filter.dynamic_slam import CrowdMap, DynamicSlam
from slam_core.filter.kernels.weights import effective_sample_size, normalise_log_weights_ess
from slam_core.filter.params import FilterParams, HumanAnchorParams, MotionParams, ResamplingParams

PARAMS = FilterParams(n_particles=20, anchors=replace(FilterParams().anchors, capacity=6))
ROOT = Path(__file__).resolve().parents[3]

operation = st.one_of(
    st.tuples(st.just("step"), st.floats(0.0, 1.5), st.floats(-4.0, 4.0)),
    st.tuples(st.just("anchor"), st.integers(0, 4), st.integers(0, 2)),
    st.tuples(st.just("encounter"), st.floats(0.0, 40.0), st.floats(0.05, 100.0)),
)


def _check(engine: DynamicSlam) -> None:
    s = engine.state
    users = engine.active_users
    w = np.exp(s.logw[users])
    assert np.all(np.isfinite(s.logw[users]))
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-9)
    for name in ("x", "y", "heading", "bias", "scale"):
        assert np.all(np.isfinite(getattr(s, name)[users])), name
    summary = engine.summaries(users)
    assert np.all(np.isfinite(summary))
    cxx, cxy, cyy = summary[:, 2], summary[:, 3], summary[:, 4]
    assert np.all(cxx > 0)
    assert np.all(cxx * cyy - cxy * cxy > 0), "estimate covariance not positive definite"
    for u in users:
        for m in range(s.n_particles):
            n = s.map_n[u, m]
            assert 0 <= n <= s.map_capacity
            cov = s.map_cov[u, m, :n]
            assert np.all(np.isfinite(cov))
            assert np.all(cov[:, 0] > 0)
            assert np.all(cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2 > 0), (
                "anchor covariance not positive definite"
            )
    assert np.all(s.ctrl_cov[users, 0] * s.ctrl_cov[users, 2] - s.ctrl_cov[users, 1] ** 2 >= -1e-12)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    ops=st.lists(operation, min_size=1, max_size=30),
    model=st.sampled_from(["paper", "bias-scale"]),
    sampling=st.sampled_from(["one-shot", "iterative"]),
    scheme=st.sampled_from(["systematic", "stratified", "residual", "multinomial"]),
    seed=st.integers(0, 2**31),
)
def test_invariants_hold_after_every_update(
    ops: list[tuple[str, float, float]], model: str, sampling: str, scheme: str, seed: int
) -> None:
    params = replace(
        PARAMS,
        motion=MotionParams(model=model),
        human=HumanAnchorParams(sampling=sampling, peer_selection="all"),
        resampling=ResamplingParams(scheme=scheme),
    )
    engine = DynamicSlam(params, seed=seed)
    users = np.array([engine.add_user(0.0, 0.0), engine.add_user(3.0, 4.0), engine.add_user(-5.0, 1.0)])
    for kind, a, b in ops:
        if kind == "step":
            engine.step(users, np.arange(4), np.full(3, a), np.full(3, b))
        elif kind == "anchor":
            engine.observe_building_anchors(users[: int(b) + 1], np.full(int(b) + 1, int(a)))
        else:
            engine.observe_encounters(users[[0, 0]], users[[1, 2]], np.array([a, a]), np.array([b, b]))
        _check(engine)


def test_resampled_indices_keep_particles_from_the_cloud() -> None:
    engine = DynamicSlam(replace(PARAMS, resampling=ResamplingParams(ess_threshold=1.0)), seed=1)
    u = engine.add_user(0.0, 0.0, position_sigma=5.0)
    before = set(engine.state.x[u].tolist())
    engine.state.logw[u] = np.log(np.r_[0.9, np.full(19, 0.1 / 19)])
    engine._resample(np.array([u]))
    after = engine.state.x[u].tolist()
    assert set(after) <= before
    assert after.count(max(after, key=after.count)) >= 15  # the heavy particle dominates


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-800.0, 50.0) | st.just(-np.inf), min_size=1, max_size=80),
)
def test_the_normalising_pass_gives_the_effective_sample_size(logs: list[float]) -> None:
    """The motion update judges a penalised user's resampling from the normalising pass's own sums: the same
    ESS as computed afresh, within rounding; an all-zero row is left alone and has none."""
    row = np.array([logs])
    before = row.copy()
    ess = normalise_log_weights_ess(row, 0)
    if not np.isfinite(before.max()):
        assert ess == 0.0
        np.testing.assert_array_equal(row, before)
        return
    assert np.isclose(np.exp(row[0]).sum(), 1.0)
    assert ess == pytest.approx(effective_sample_size(row, 0), rel=1e-12)
    assert 1.0 - 1e-9 <= ess <= len(logs) * (1.0 + 1e-9)


def test_map_overflow_is_counted_not_silent() -> None:
    engine = DynamicSlam(replace(PARAMS, anchors=replace(PARAMS.anchors, capacity=2)), seed=0)
    u = engine.add_user(0.0, 0.0)
    for k in range(4):  # anchors 20 m apart: each is new
        engine.step(np.array([u]), np.array([0, 1]), np.array([20.0]), np.array([0.0]))
        engine.observe_building_anchors(np.array([u]), np.array([k % 5]))
    assert np.all(engine.state.map_n[u] == 2)
    assert engine.state.n_map_overflow[u] > 0


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda e, u: e.step(np.array([u]), np.array([0, 1]), np.array([np.nan]), np.array([0.0])), "finite"),
        (lambda e, u: e.step(np.array([u]), np.array([0, 2]), np.array([0.7]), np.array([0.0])), "offsets"),
        (lambda e, u: e.step(np.array([u, u]), np.array([0, 1, 2]), np.ones(2), np.zeros(2)), "only once"),
        (lambda e, u: e.step(np.array([99]), np.array([0, 1]), np.ones(1), np.zeros(1)), "unknown user"),
        (lambda e, u: e.observe_building_anchors(np.array([u]), np.array([7])), "detected types"),
        (lambda e, u: e.observe_encounters(np.array([u]), np.array([u]), np.ones(1), np.ones(1)), "itself"),
        (
            lambda e, u: e.observe_encounters(np.array([u]), np.array([0]), np.ones(1), np.zeros(1)),
            "variances",
        ),
        (
            lambda e, u: e.observe_encounters(np.array([u]), np.array([0]), np.full(1, np.inf), np.ones(1)),
            "finite",
        ),
        (
            lambda e, u: e.observe_encounters(
                np.array([u]), np.array([0]), np.ones(1), np.ones(1), np.ones(2)
            ),
            "offset must have shape",
        ),
        (
            lambda e, u: e.observe_encounters(
                np.array([u]), np.array([0]), np.ones(1), np.ones(1), np.array([[np.nan, 0.0]])
            ),
            "offsets must be finite",
        ),
        (lambda e, u: e.add_user(np.nan, 0.0), "finite"),
    ],
)
def test_bad_input_raises_and_changes_nothing(call, message: str) -> None:  # type: ignore[no-untyped-def]
    engine = DynamicSlam(PARAMS, seed=0)
    engine.add_user(0.0, 0.0)
    u = engine.add_user(1.0, 1.0)
    before = {k: v.copy() for k, v in vars(engine.state).items()}
    with pytest.raises(ValueError, match=message):
        call(engine, u)
    for k, v in vars(engine.state).items():
        np.testing.assert_array_equal(v, before[k], err_msg=k)


@pytest.mark.parametrize(
    ("factory", "message"),
    [
        (lambda: MotionParams(model="kalman"), "valid: paper, bias-scale"),
        (lambda: HumanAnchorParams(sampling="twice"), "valid: one-shot, iterative"),
        (lambda: ResamplingParams(scheme="lottery"), "valid: systematic, stratified, residual, multinomial"),
        (lambda: HumanAnchorParams(peer_selection="loudest"), "valid: most-confident, all"),
    ],
)
def test_unknown_names_list_the_valid_ones(factory, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=message):
        factory()


def test_users_come_and_go_and_slots_grow() -> None:
    engine = DynamicSlam(PARAMS, seed=0, initial_capacity=2)
    slots = [engine.add_user(float(i), 0.0) for i in range(5)]
    assert engine.state.capacity >= 5
    engine.remove_user(slots[1])
    assert slots[1] not in engine.active_users
    again = engine.add_user(0.0, 0.0)
    assert again == slots[1]
    with pytest.raises(ValueError, match="unknown user"):
        engine.summaries(np.array([engine.state.capacity + 3]))


def test_crowd_map_seeds_every_particle() -> None:
    crowd = CrowdMap(
        np.array([[1.0, 2.0]]), np.array([[0.3, 0.0, 0.3]]), np.array([1]), np.array([True]), np.array([42])
    )
    engine = DynamicSlam(PARAMS, seed=0)
    u = engine.add_user(0.0, 0.0, crowd_map=crowd)
    assert np.all(engine.state.map_n[u] == 1)
    assert np.all(engine.state.map_crowd_id[u, :, 0] == 42)
    assert np.all(engine.state.map_known[u, :, 0])
    with pytest.raises(ValueError, match="positive definite"):
        CrowdMap(
            np.array([[1.0, 2.0]]),
            np.array([[0.0, 0.0, 0.3]]),
            np.array([1]),
            np.array([True]),
            np.array([1]),
        )


_DETERMINISM_SCRIPT = """
import numpy as np
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.filter.params import FilterParams
e = DynamicSlam(FilterParams(n_particles=30), seed=123, parallel_min_users=1)  # every call in parallel
users = np.array([e.add_user(float(i), float(-i)) for i in range(40)])
rng = np.random.default_rng(0)
for t in range(30):
    e.step(users, np.arange(41), 0.7 + 0.05 * rng.standard_normal(40), rng.uniform(-3, 3, 40))
    if t % 5 == 0:
        e.observe_building_anchors(users[::3], rng.integers(0, 5, users[::3].size))
        e.observe_encounters(users[0:10], users[10:20], rng.uniform(0, 5, 10), np.full(10, 4.0))
print(e.summaries(users).tobytes().hex())
"""


def test_same_seed_same_estimates_on_one_and_two_threads() -> None:
    outputs = []
    for threads in ("1", "2"):
        env = {**os.environ, "NUMBA_NUM_THREADS": threads}
        run = subprocess.run(
            [sys.executable, "-c", _DETERMINISM_SCRIPT],
            capture_output=True,
            text=True,
            env=env,
            cwd=ROOT,
            check=True,
        )
        outputs.append(run.stdout.strip())
    assert outputs[0] == outputs[1]
    assert len(outputs[0]) > 100


def _run_operations(parallel_min_users: int) -> DynamicSlam:
    """Every kernel with a serial twin (motion, building anchors, crowd merge, encounters, resampling,
    summaries) over 12 users, always resampling."""
    params = replace(PARAMS, resampling=ResamplingParams(ess_threshold=1.0))
    engine = DynamicSlam(params, seed=7, parallel_min_users=parallel_min_users)
    users = np.array([engine.add_user(float(i), float(-i)) for i in range(12)])
    rng = np.random.default_rng(3)
    crowd = CrowdMap(
        mean=np.array([[2.0, 1.0], [8.0, -3.0]]),
        cov=np.array([[0.5, 0.0, 0.5], [1.0, 0.1, 1.0]]),
        type=np.array([0, 3]),
        known=np.array([True, False]),
        crowd_id=np.array([0, 1]),
    )
    for t in range(12):
        engine.step(users, np.arange(13), 0.7 + 0.05 * rng.standard_normal(12), rng.uniform(-3, 3, 12))
        if t % 3 == 0:
            engine.observe_building_anchors(users[t % 2 :: 2], rng.integers(0, 5, 6))
            engine.observe_encounters(users[0:4], users[4:8], rng.uniform(0, 5, 4), np.full(4, 4.0))
        if t == 5:
            engine.merge_crowd_map(users, crowd)
    return engine


def test_serial_twins_give_the_parallel_kernels_numbers() -> None:
    """Small calls run the serial twins (``slam_core.filter.kernels.serial``): the same state, bit for bit."""
    parallel, serial = _run_operations(parallel_min_users=1), _run_operations(parallel_min_users=10**9)
    for name in ("x", "y", "heading", "bias", "scale", "logw", "ctrl_cov", "map_mu", "map_cov", "map_n"):
        np.testing.assert_array_equal(
            getattr(parallel.state, name), getattr(serial.state, name), err_msg=name
        )
    users = parallel.active_users
    np.testing.assert_array_equal(parallel.summaries(users), serial.summaries(users))
    # the means alone are the summaries' first columns, bit for bit, in both kernels
    np.testing.assert_array_equal(parallel.means(users), parallel.summaries(users)[:, 0:2])
    np.testing.assert_array_equal(serial.means(users), serial.summaries(users)[:, 0:2])
    assert parallel.state.n_resamples[users].min() >= 1  # every user observed something, and resampled
    assert parallel.state.map_n[users].min() >= 2  # the crowd's anchors were merged


def test_calls_under_the_threshold_take_the_serial_twins() -> None:
    from slam_core.filter.kernels import building, human, motion, resampling, summary
    from slam_core.filter.kernels.serial import pick

    assert pick("parallel", "serial", 255, 256) == "serial"
    assert pick("parallel", "serial", 256, 256) == "parallel"
    pairs: list[tuple[Any, Any]] = [
        (summary.summarise, summary.summarise_serial),
        (summary.weighted_means, summary.weighted_means_serial),
        (motion.motion_update, motion.motion_update_serial),
        (resampling.resample_users, resampling.resample_users_serial),
        (human.human_anchor_update, human.human_anchor_update_serial),
        (building.building_anchor_update, building.building_anchor_update_serial),
        (building.merge_crowd_anchors, building.merge_crowd_anchors_serial),
    ]
    for kernel, twin in pairs:
        assert kernel.targetoptions.get("parallel")
        assert not twin.targetoptions.get("parallel")
        assert twin.targetoptions.get("nogil")
        assert twin.py_func.__code__ is kernel.py_func.__code__
        # numba's cache files are named after the qualified name: the two compilations must not share one
        assert twin.py_func.__qualname__ == kernel.py_func.__qualname__ + "_serial"


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.integers(0, 8), min_size=1, max_size=25), st.integers(0, 2**32 - 1))
def test_kept_means_follow_every_change_of_the_particles(operations: list[int], seed: int) -> None:
    """``means`` keeps each user's mean until its particles change: after any sequence of every kind of
    update, admission (the state growing), removal and pickling, it equals the summaries' first columns,
    bit for bit."""
    import pickle

    rng = np.random.default_rng(seed)
    engine = DynamicSlam(FilterParams(n_particles=16), seed=1, initial_capacity=2)
    users = [engine.add_user(0.0, 0.0), engine.add_user(3.0, 1.0)]

    def check() -> None:
        slots = np.array(users, dtype=np.int64)
        np.testing.assert_array_equal(engine.means(slots), engine.summaries(slots)[:, 0:2])

    check()
    for op in operations:
        some = np.array(sorted(set(rng.choice(users, size=min(len(users), 2), replace=False).tolist())))
        if op == 0:
            users.append(engine.add_user(*rng.uniform(-5, 5, 2)))  # the state grows past two
        elif op == 1:
            engine.step(
                some, np.arange(some.size + 1), np.full(some.size, 0.7), rng.uniform(-3, 3, some.size)
            )
        elif op == 2:
            engine.observe_building_anchors(some, rng.integers(0, 5, some.size))
        elif op == 3:
            engine.shift(some, rng.uniform(-1, 1, (some.size, 2)))
        elif op == 4:
            engine.observe_position(some, rng.uniform(-50, 50, (some.size, 2)), np.full(some.size, 1.0))
        elif op == 5:
            engine.observe_position_robust(some, rng.uniform(-5, 5, (some.size, 2)), 3.0, 0.2, 30.0)
        elif op == 6 and some.size == 2:
            engine.observe_encounters(some[:1], some[1:], np.array([2.0]), np.array([1.0]))
        elif op == 7 and len(users) > 2:
            engine.remove_user(users.pop(0))
            users.append(engine.add_user(1.0, 1.0))  # the freed slot, reused
        elif op == 8:
            engine = pickle.loads(pickle.dumps(engine))
        check()


class _FullMaps(DynamicSlam):
    MAP_START = 1 << 20  # room for every anchor from the start, as the state was allocated before


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.integers(0, 5), min_size=4, max_size=30), st.integers(0, 2**32 - 1))
def test_maps_sized_by_use_change_no_filter(operations: list[int], seed: int) -> None:
    """Particle maps that start with room for a few anchors and grow before each call that may add some
    give the same filters, bit for bit, as maps with room for all from the start: summaries, every
    particle's map up to its length, and the overflow counts at the capacity; through anchor observations,
    crowd-map merges, steps, new users (the slots growing) and pickling."""
    import pickle

    rng = np.random.default_rng(seed)
    params = replace(PARAMS, anchors=replace(PARAMS.anchors, capacity=6))
    crowd = CrowdMap(
        rng.uniform(-5, 5, (3, 2)), np.tile([0.3, 0.0, 0.3], (3, 1)), np.array([1, 2, 3]),
        np.array([True, False, False]), np.array([7, 8, 9]),
    )  # fmt: skip
    lazy, full = (
        DynamicSlam(params, seed=5, initial_capacity=2),
        _FullMaps(params, seed=5, initial_capacity=2),
    )
    assert lazy.state.map_capacity == DynamicSlam.MAP_START < 6 == full.state.map_capacity
    users: list[int] = []
    for op in [0, 0, *operations]:
        some = np.array(sorted(set(rng.choice(users, size=min(len(users), 2), replace=False).tolist())))
        start, headings, types = (
            rng.uniform(-5, 5, 2),
            rng.uniform(-3, 3, some.size),
            rng.integers(0, 5, some.size),
        )
        for engine in (lazy, full):
            if op == 0:
                slot = engine.add_user(
                    float(start[0]), float(start[1]), crowd_map=crowd if len(users) % 2 else None
                )
            elif op == 1 and some.size:
                engine.step(some, np.arange(some.size + 1), np.full(some.size, 0.7), headings)
            elif op in (2, 3) and some.size:
                engine.observe_building_anchors(some, types)
            elif op == 4 and some.size:
                engine.merge_crowd_map(some, crowd)
        if op == 0:
            users.append(slot)
        if op == 5:
            lazy = pickle.loads(pickle.dumps(lazy))
        _same_filters(lazy, full, users)
    for k in range(8):  # every user walks past eight new anchors (five types): maps fill up and overflow
        slots = np.array(users, dtype=np.int64)
        for engine in (lazy, full):
            engine.step(slots, np.arange(slots.size + 1), np.full(slots.size, 3.0), np.full(slots.size, 0.5))
            engine.observe_building_anchors(slots, np.full(slots.size, k % 5))
        _same_filters(lazy, full, users)
    assert full.state.n_map_overflow.sum() > 0
    assert lazy.state.map_capacity == 6


def _same_filters(lazy: DynamicSlam, full: DynamicSlam, users: list[int]) -> None:
    slots = np.array(users, dtype=np.int64)
    np.testing.assert_array_equal(lazy.summaries(slots), full.summaries(slots))
    a, b = lazy.state, full.state
    np.testing.assert_array_equal(a.map_n[slots], b.map_n[slots])
    np.testing.assert_array_equal(a.n_map_overflow[slots], b.n_map_overflow[slots])
    for u in users:
        for m in range(a.n_particles):
            n = a.map_n[u, m]
            np.testing.assert_array_equal(a.map_mu[u, m, :n], b.map_mu[u, m, :n])
            np.testing.assert_array_equal(a.map_crowd_id[u, m, :n], b.map_crowd_id[u, m, :n])


def test_an_encounter_offset_is_the_peer_moved_by_it() -> None:
    """``offset`` carries an encounter to now: a's update against b with offset o is a's update against b
    standing o further along, and b's is the same with b translated back by o (same seeds: same draws)."""
    offset = np.array([[1.5, -2.0]])

    def run(b_xy: tuple[float, float], o: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        engine = DynamicSlam(PARAMS, seed=4)
        a = engine.add_user(0.0, 0.0, 0.0, 1.0)
        b = engine.add_user(*b_xy, 0.0, 1.5)
        outcome = engine.observe_encounters(np.array([a]), np.array([b]), np.array([3.0]), np.array([1.0]), o)
        s = engine.state
        return np.stack([s.x[a], s.y[a]]), np.stack([s.x[b], s.y[b]]), outcome.mahalanobis

    a_placed, b_placed, m_placed = run((4.0, 1.0), offset)
    a_moved, b_moved, m_moved = run((4.0 + 1.5, 1.0 - 2.0), None)
    np.testing.assert_allclose(a_placed, a_moved, atol=1e-9)
    np.testing.assert_allclose(b_placed + offset.T, b_moved, atol=1e-9)
    np.testing.assert_allclose(m_placed, m_moved)
    a_now, _, m_now = run((4.0, 1.0), None)
    assert not np.allclose(a_now, a_placed)  # the offset does change the update
    assert m_now[0] != m_placed[0]
