"""The floor plan's grid as a heading observation: the grid found from the walls, straight stretches cut from
the steps, the particles weighed as the likelihood says, and a biased phone's heading corrected."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from slam_core.encounters.models import Calibration, RangeModel
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.filter.floor_plan import PlanIndex, dominant_axis
from slam_core.filter.params import FilterParams, FloorPlanParams, ResamplingParams
from slam_core.tracking.stretches import StraightStretches
from slam_core.tracking.tracker import BuildingTracker, TrackerParams, UserBatch

GRID = math.radians(30.0)


def _rotated(points: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return points @ np.array([[c, s], [-s, c]])


def _hall(angle: float = GRID, half: float = 150.0) -> PlanIndex:
    """A square hall 300 m across, turned by ``angle``: its four walls are its grid, far from the walker."""
    corners = _rotated(np.array([[-half, -half], [half, -half], [half, half], [-half, half]]), angle)
    walls = np.hstack([corners, np.roll(corners, -1, axis=0)])
    return PlanIndex.build(walls, [corners])


def test_the_grid_is_the_walls_direction_modulo_90_degrees() -> None:
    axis, strength = dominant_axis(_hall(math.radians(110.0)).walls)  # 110 = 20 modulo 90
    assert axis == pytest.approx(math.radians(20.0), abs=1e-9)
    assert strength == pytest.approx(1.0)
    # a short wall off the grid pulls the axis by its share of the length
    walls = np.vstack([_hall(0.0, 10.0).walls, [[0.0, 0.0, 8.0 * math.cos(0.2), 8.0 * math.sin(0.2)]]])
    axis, strength = dominant_axis(walls)
    assert 0.0 < axis < 0.2 / 4
    assert 0.8 < strength < 1.0
    rng = np.random.default_rng(3)
    angles = rng.uniform(0, 2 * math.pi, 4000)
    scattered = np.column_stack([np.zeros((4000, 2)), np.cos(angles), np.sin(angles)])
    assert dominant_axis(scattered)[1] < 0.05
    assert dominant_axis(np.zeros((0, 4))) == (0.0, 0.0)
    assert PlanIndex.empty().axis_strength == 0.0


def test_stretches_are_cut_at_turns_and_every_stretch_length() -> None:
    stretches = StraightStretches(length_m=10.0, turn_rad=math.radians(20.0))
    wiggle = 1.0 + np.radians(np.tile([8.0, -8.0], 15))  # 30 steps of 0.7 m, +-8 degrees about 1 rad
    done = stretches.add("a", np.full(30, 0.7), wiggle)
    assert len(done) == 2  # 21 m: two stretches of 10 m (15 steps each), none left open
    assert done == pytest.approx([1.0, 1.0], abs=0.01)  # an odd count of wiggles leans 8 / 15 degrees
    # a turn starts a new stretch: 7 m, a right angle, 7 m complete nothing
    assert stretches.add("b", np.full(20, 0.7), np.r_[np.zeros(10), np.full(10, math.pi / 2)]) == []
    assert stretches.add("b", np.full(5, 0.7), np.full(5, math.pi / 2)) == [pytest.approx(math.pi / 2)]
    # a stretch carries over between calls and standing still (zero-length steps) does not end it
    assert stretches.add("c", np.full(10, 0.7), np.zeros(10)) == []
    assert stretches.add("c", np.zeros(3), np.full(3, 2.0)) == []
    assert stretches.add("c", np.full(5, 0.7), np.zeros(5)) == [pytest.approx(0.0)]
    stretches.forget("c")
    stretches.forget("never-seen")
    assert len(stretches) == 2
    with pytest.raises(ValueError, match="must be > 0"):
        StraightStretches(0.0, 0.1)
    with pytest.raises(ValueError, match="axis_share"):
        FloorPlanParams(axis_share=1.0)
    with pytest.raises(ValueError, match="stretch_m"):
        FloorPlanParams(stretch_m=0.0)


def _engine(plan: PlanIndex | None, ess_threshold: float = 0.5, seed: int = 0) -> tuple[DynamicSlam, int]:
    params = FilterParams(resampling=ResamplingParams(ess_threshold=ess_threshold))
    engine = DynamicSlam(params, seed=seed)
    engine.set_floor_plan(0, plan)
    u = engine.add_user(0.0, 0.0, heading=0.0, position_sigma=0.3)
    return engine, u


def test_particles_are_weighed_by_the_likelihood_of_their_stretch() -> None:
    engine, u = _engine(_hall(), ess_threshold=1e-9)  # no resampling: the weights show the likelihood
    engine.step(np.array([u]), np.array([0, 1]), np.array([0.7]), np.array([GRID + 0.1]))
    s = engine.state
    before = s.logw[u].copy()
    error = s.heading[u] - s.last_obs_heading[u]
    engine.observe_heading_axis(np.array([u]), np.array([GRID + 0.1]))
    fp = FloorPlanParams()
    delta = np.array([math.remainder(GRID + 0.1 + e - GRID, math.pi / 2) for e in error])
    gauss = np.exp(-0.5 * (delta / fp.axis_sigma_rad) ** 2) / math.sqrt(2 * math.pi) / fp.axis_sigma_rad
    expected = before + np.log(fp.axis_share * gauss + (1 - fp.axis_share) / (math.pi / 2))
    expected -= np.logaddexp.reduce(expected)
    np.testing.assert_allclose(s.logw[u], expected, atol=1e-12)
    assert np.isclose(np.exp(s.logw[u]).sum(), 1.0)
    # a particle whose error turns the stretch onto the grid gains on one that turns it off
    on, off = int(np.argmin(np.abs(delta))), int(np.argmax(np.abs(delta)))
    assert s.logw[u, on] - before[on] > s.logw[u, off] - before[off]


def test_without_a_grid_the_weights_do_not_change() -> None:
    rng = np.random.default_rng(4)
    angles = rng.uniform(0, 2 * math.pi, 400)
    scattered = PlanIndex.build(
        np.column_stack([rng.uniform(-50, 50, (400, 2)), np.cos(angles), np.sin(angles)])
    )
    assert scattered.axis_strength < FloorPlanParams().axis_min_strength
    for plan in (None, scattered):
        engine, u = _engine(plan, ess_threshold=1e-9)
        engine.step(np.array([u]), np.array([0, 1]), np.array([0.7]), np.array([0.3]))
        before = engine.state.logw.copy()
        engine.observe_heading_axis(np.array([u]), np.array([0.3]))
        np.testing.assert_array_equal(engine.state.logw, before)
    # a user without a step yet has no heading error to weigh
    engine, u = _engine(_hall())
    before = engine.state.logw.copy()
    engine.observe_heading_axis(np.array([u]), np.array([0.3]))
    np.testing.assert_array_equal(engine.state.logw, before)


def test_bad_stretches_are_refused_and_change_nothing() -> None:
    engine, u = _engine(_hall())
    engine.step(np.array([u]), np.array([0, 1]), np.array([0.7]), np.array([0.3]))
    before = engine.state.logw.copy()
    with pytest.raises(ValueError, match="one finite stretch heading per user"):
        engine.observe_heading_axis(np.array([u]), np.array([math.nan]))
    with pytest.raises(ValueError, match="one finite stretch heading per user"):
        engine.observe_heading_axis(np.array([u]), np.array([0.1, 0.2]))
    with pytest.raises(ValueError, match="unknown user slot"):
        engine.observe_heading_axis(np.array([u + 5]), np.array([0.1]))
    np.testing.assert_array_equal(engine.state.logw, before)


def _heading_error(engine: DynamicSlam, u: int) -> float:
    """The weighted mean of the particles' heading errors (their bias and walk), in degrees."""
    s = engine.state
    error = np.array([math.remainder(e, 2 * math.pi) for e in s.heading[u] - s.last_obs_heading[u]])
    return math.degrees(float(np.exp(s.logw[u]) @ error))


def _walk(plan: PlanIndex | None, observe: bool, seed: int) -> float:
    """A walker goes 100 m along the grid while its phone reads 10 degrees left of it; returns the particles'
    mean heading error at the end (the truth is -10 degrees)."""
    engine, u = _engine(plan, seed=seed)
    measured = GRID + math.radians(10.0)
    for k in range(140):
        engine.step(np.array([u]), np.array([0, 1]), np.array([0.7]), np.array([measured]))
        if observe and k % 21 == 20:  # a stretch every 14.7 m
            engine.observe_heading_axis(np.array([u]), np.array([measured]))
        s = engine.state
        assert np.all(np.isfinite(s.logw[u]))
        assert np.isclose(np.exp(s.logw[u]).sum(), 1.0)
    return _heading_error(engine, u)


def test_a_biased_phone_walking_the_grid_has_its_heading_error_found() -> None:
    for seed in range(3):
        assert abs(_walk(_hall(), observe=False, seed=seed)) < 5.0  # the prior alone: no idea of the bias
        assert _walk(_hall(), observe=True, seed=seed) == pytest.approx(-10.0, abs=3.0)


def _batch(t0: int, n: int, azimuth: float, fix: bool) -> UserBatch:
    """``n`` 0.7 m steps along the azimuth (clockwise from north), with a fix at the origin first."""
    fields: dict[str, object] = {}
    if fix:
        fields = {
            "fix_t": np.array([t0], dtype=np.int64),
            "fix_xy": np.array([[0.0, 0.0]]),
            "fix_sigma": np.array([0.3]),
            "fix_azimuth": np.array([azimuth]),
        }
    return UserBatch(
        user="u",
        step_t=(t0 + 500 * (1 + np.arange(n))).astype(np.int64),
        step_length=np.full(n, 0.7),
        step_azimuth=np.full(n, azimuth),
        step_turn=np.full(n, np.nan),
        **fields,  # type: ignore[arg-type]
    )


def test_the_tracker_observes_its_users_stretches_only_when_asked() -> None:
    cal = Calibration(RangeModel("wifi-log", (0.0, 2.0), 3.0), RangeModel("bt", (-60.0, -9.0, 0.0), 2.8))
    azimuth = math.pi / 2 - (GRID + math.radians(10.0))  # the phone reads 10 degrees left of the grid
    ends = {}
    for on in (False, True):
        base = TrackerParams()
        params = replace(
            base, filter=replace(base.filter, floor_plan=replace(base.filter.floor_plan, heading_axes=on))
        )
        tracker = BuildingTracker(params, cal, seed=1)
        tracker.set_floor_plan(_hall())
        t0 = 1_700_000_000_000
        for k in range(10):
            tracker.apply([_batch(t0 + 10_000 * k, 20, azimuth, fix=k == 0)])
        ends[on] = _heading_error(tracker.filters, tracker._users["u"].slot)
        tracker.remove_user("u")
        assert not tracker._stretches  # a removed user's open stretch goes with it (none kept when off)
    assert abs(ends[False]) < 5.0
    assert ends[True] == pytest.approx(-10.0, abs=3.0)
