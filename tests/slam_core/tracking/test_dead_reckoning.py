"""The tracker's plain dead reckoning: steps from the PDR front-end's gyroscope heading are re-rotated by the
latest north offset; steps that carry none (a phone's own) add up as sent."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.encounters.models import Calibration, RangeModel
from slam_core.tracking.tracker import BuildingTracker, TrackerParams, UserBatch

T0 = 1_700_000_000_000
CAL = Calibration(
    RangeModel("wifi-log", (0.0, 2.0), 3.0), RangeModel("bt-quadratic", (-60.0, -10.0, 0.0), 4.0)
)


def _steps(t0: int, n: int, azimuth: float, offset: float | None, fix: bool) -> UserBatch:
    """``n`` 1 m steps in the azimuth (clockwise from north) with the front-end's offset (None: none)."""
    fields: dict[str, object] = {}
    if fix:
        fields = {
            "fix_t": np.array([t0], dtype=np.int64),
            "fix_xy": np.array([[5.0, 7.0]]),
            "fix_sigma": np.array([0.5]),
            "fix_azimuth": np.array([azimuth]),
        }
    return UserBatch(
        user="u",
        step_t=(t0 + 500 * (1 + np.arange(n))).astype(np.int64),
        step_length=np.ones(n),
        step_azimuth=np.full(n, azimuth),
        step_turn=np.full(n, np.nan),
        step_heading_offset=np.full(n, np.nan if offset is None else offset),
        **fields,  # type: ignore[arg-type]
    )


def _dr(tracker: BuildingTracker) -> np.ndarray:
    position = tracker.dead_reckoning("u")
    assert position is not None
    return position


def test_latest_offset_turns_the_whole_path_walked() -> None:
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    tracker.apply([_steps(T0, 10, math.pi / 2, 0.0, fix=True)])
    np.testing.assert_allclose(_dr(tracker), np.array([15.0, 7.0]), atol=1e-9)
    # the front-end's north offset grew by 0.1 rad: the relative yaw is still east, the path turns with it
    tracker.apply([_steps(T0 + 10_000, 10, math.pi / 2 + 0.1, 0.1, fix=False)])
    turned = 20.0 * np.array([math.sin(math.pi / 2 + 0.1), math.cos(math.pi / 2 + 0.1)])
    np.testing.assert_allclose(_dr(tracker), np.array([5.0, 7.0]) + turned, atol=1e-9)


def test_steps_without_offset_add_up_as_sent() -> None:
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    tracker.apply([_steps(T0, 10, math.pi / 2, None, fix=True)])
    tracker.apply([_steps(T0 + 10_000, 10, 0.0, None, fix=False)])
    np.testing.assert_allclose(_dr(tracker), np.array([15.0, 17.0]), atol=1e-9)
    assert tracker.dead_reckoning("nobody") is None


def test_offsets_must_match_the_steps() -> None:
    batch = _steps(T0, 3, 0.0, 0.0, fix=True)
    with pytest.raises(ValueError, match="inconsistent array shapes"):
        UserBatch(**{**batch.__dict__, "step_heading_offset": np.zeros(2)})


@pytest.mark.parametrize("bad_type", [-1, 99])
def test_a_batch_with_an_unknown_anchor_type_is_refused_and_changes_nothing(bad_type: int) -> None:
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    tracker.apply([_steps(T0, 3, 0.0, None, fix=True)])
    before = _dr(tracker).copy()
    later = _steps(T0 + 5_000, 3, 0.0, None, fix=False)
    bad = UserBatch(
        **{
            **later.__dict__,
            "detect_t": np.array([T0 + 5_100], dtype=np.int64),
            "detect_type": np.array([bad_type]),
        }
    )
    with pytest.raises(ValueError, match="anchor type outside"):
        tracker.apply([bad])
    np.testing.assert_array_equal(_dr(tracker), before)
    tracker.apply([later])  # the same steps without the detection are taken
    assert not np.array_equal(_dr(tracker), before)


def _estimate(tracker: BuildingTracker) -> np.ndarray:
    row = tracker.estimate("u")
    assert row is not None
    return np.array([row.x, row.y])


def _pair(second_fix: bool) -> tuple[np.ndarray, np.ndarray]:
    """The same walk through a tracker that revises and one that does not: their estimates."""
    out = []
    for revise in (True, False):
        tracker = BuildingTracker(TrackerParams(revise_headings=revise), CAL, seed=4)
        tracker.apply([_steps(T0, 10, math.pi / 2, 0.0, fix=True)])
        second = _steps(T0 + 10_000, 10, math.pi / 2 + 0.1, 0.1, fix=False)
        if second_fix:  # an absolute observation where the filter already is, before the turned steps
            where = _estimate(tracker)
            second = UserBatch(
                **{
                    **second.__dict__,
                    "fix_t": np.array([T0 + 10_000], dtype=np.int64),
                    "fix_xy": where[None, :],
                    "fix_sigma": np.array([3.0]),
                    "fix_azimuth": np.array([math.nan]),
                }
            )
        tracker.apply([second])
        out.append(_estimate(tracker))
    return out[0], out[1]


def test_filter_is_moved_by_the_revision_of_the_path_since_the_last_fix() -> None:
    revised, plain = _pair(second_fix=False)
    # the first ten metres east were laid with offset 0; at offset 0.1 they turn 0.1 rad clockwise
    expected = 10.0 * np.array([math.cos(0.1) - 1.0, -math.sin(0.1)])
    np.testing.assert_allclose(revised - plain, expected, atol=1e-9)
    # after an absolute observation the path before it is not revised
    revised, plain = _pair(second_fix=True)
    np.testing.assert_allclose(revised, plain, atol=1e-9)


def test_engine_shift_translates_particles_and_checks_its_input() -> None:
    tracker = BuildingTracker(TrackerParams(), CAL, seed=4)
    tracker.apply([_steps(T0, 3, 0.0, None, fix=True)])
    engine = tracker.filters
    slot = np.flatnonzero(engine.state.active)
    before = (engine.state.x[slot].copy(), engine.state.y[slot].copy(), engine.state.logw[slot].copy())
    engine.shift(slot, np.array([[1.5, -2.0]]))
    np.testing.assert_allclose(engine.state.x[slot], before[0] + 1.5)
    np.testing.assert_allclose(engine.state.y[slot], before[1] - 2.0)
    np.testing.assert_array_equal(engine.state.logw[slot], before[2])
    for bad in (np.array([[math.nan, 0.0]]), np.zeros((2, 2))):
        with pytest.raises(ValueError, match="one finite shift"):
            engine.shift(slot, bad)
    with pytest.raises(ValueError, match="unknown user slot"):
        engine.shift(np.array([99]), np.zeros((1, 2)))
    np.testing.assert_allclose(engine.state.x[slot], before[0] + 1.5)


def test_a_clock_that_jumps_back_restarts_the_users_timeline() -> None:
    """A phone whose clock is set back by two hours: its next batches are not skipped as out of order
    until the clock catches up; the timeline restarts there, position and filter kept. A batch only a
    little behind (a late batch) is still out of order, its steps skipped."""
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    tracker.apply([_steps(T0, 10, math.pi / 2, None, fix=True)])
    np.testing.assert_allclose(_dr(tracker), np.array([15.0, 7.0]), atol=1e-9)
    late = tracker.apply([_steps(T0 - 5_000, 4, math.pi / 2, None, fix=False)]).reports["u"]
    assert late.steps_dropped == 4
    assert not late.clock_restarted
    back = T0 - 2 * 3600 * 1000
    report = tracker.apply([_steps(back, 10, 0.0, None, fix=False)]).reports["u"]
    assert report.clock_restarted
    assert report.steps_applied == 10
    np.testing.assert_allclose(_dr(tracker), np.array([15.0, 17.0]), atol=1e-9)  # 10 m north of where it was
    assert tracker.last_time_ms("u") == back + 5_000
    going_on = tracker.apply([_steps(back + 5_000, 2, 0.0, None, fix=False)]).reports["u"]
    assert going_on.steps_applied == 2
    assert not going_on.clock_restarted
