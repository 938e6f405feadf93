"""The online PDR front-end on a real walk: batch-split invariance for every orientation source, the
Madgwick start against the phone's rotation vector, stale samples, and every error path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.sensing.pdr.online import ImuSamples, PdrParams, PdrState, PdrSteps, drop_stale, pdr_steps
from tests.conftest import SAMPLE_FLOOR

pytestmark = pytest.mark.walks

WALKS = SAMPLE_FLOOR / "path_data_files"
PARAMS = PdrParams()
TURNING = "5ddb9632c5b77e0006b179b1"  # 27 steps, turns through ~120 deg


def _walk(name: str = "5dd9fd499191710006b570de") -> dict[str, np.ndarray]:
    from server.datasets.msindoor import read_trace  # the reader lives at the I/O edge

    trace = read_trace(WALKS / f"{name}.txt")
    rv = trace.streams["rotation_vector"]
    return {
        "acc": trace.streams["accelerometer"],
        "gyr": trace.streams["gyroscope"],
        "mag": trace.streams["magnetometer"],
        "rv": np.column_stack([rv, np.full(len(rv), np.nan)]),
        "waypoints": trace.waypoints,
    }


def _imu(
    walk: dict[str, np.ndarray], sources: tuple[str, ...], lo: float = -math.inf, hi: float = math.inf
) -> ImuSamples:
    def cut(rows: np.ndarray) -> np.ndarray:
        return rows[(rows[:, 0] >= lo) & (rows[:, 0] < hi)]

    empty = {"gyr": np.zeros((0, 4)), "mag": np.zeros((0, 4)), "rv": np.zeros((0, 5))}
    chosen = {k: cut(walk[k]) for k in sources}
    return ImuSamples(acc=cut(walk["acc"]), **{**empty, **chosen})


def _batched(walk: dict[str, np.ndarray], sources: tuple[str, ...], window_ms: float) -> PdrSteps:
    state = PdrState()
    parts = []
    start = walk["acc"][0, 0]
    while start <= walk["acc"][-1, 0]:
        parts.append(pdr_steps(state, _imu(walk, sources, start, start + window_ms), PARAMS))
        start += window_ms
    return PdrSteps(*(np.concatenate([getattr(p, f) for p in parts]) for f in PdrSteps.__dataclass_fields__))


@pytest.mark.parametrize("sources", [("rv",), ("rv", "gyr"), ("gyr", "mag"), ("gyr",), ()])
def test_one_second_batches_give_the_steps_of_the_whole_walk(sources: tuple[str, ...]) -> None:
    walk = _walk()
    whole = pdr_steps(PdrState(), _imu(walk, sources), PARAMS)
    batched = _batched(walk, sources, 1000.0)
    assert whole.t_ms.size > 10
    for name in PdrSteps.__dataclass_fields__:
        np.testing.assert_allclose(getattr(batched, name), getattr(whole, name), rtol=1e-9, atol=1e-9)


def test_absolute_sources_give_azimuths_and_relative_ones_turns() -> None:
    walk = _walk(TURNING)
    absolute = pdr_steps(PdrState(), _imu(walk, ("rv",)), PARAMS)
    relative = pdr_steps(PdrState(), _imu(walk, ("gyr",)), PARAMS)
    none = pdr_steps(PdrState(), _imu(walk, ()), PARAMS)
    assert np.all(np.isfinite(absolute.azimuth_rad))
    assert np.all(np.isnan(absolute.turn_rad))
    assert np.all(np.isnan(relative.azimuth_rad))
    assert np.all(np.isfinite(relative.turn_rad))
    assert np.all(np.abs(relative.turn_rad) <= math.pi)
    # the gyroscope's turns add up to the rotation vector's change of direction over the walk
    rv_change = (absolute.azimuth_rad[-1] - absolute.azimuth_rad[0] + math.pi) % (2 * math.pi) - math.pi
    assert abs(rv_change) > math.radians(90)
    gyro_change = -np.sum(relative.turn_rad[1:])
    assert abs((gyro_change - rv_change + math.pi) % (2 * math.pi) - math.pi) < math.radians(25)
    # tilt only: steps without direction, counted like the others
    assert np.all(np.isnan(none.azimuth_rad))
    assert abs(none.t_ms.size - absolute.t_ms.size) <= 3
    for steps in (absolute, relative, none):
        assert np.all((steps.length_m >= 0.1) & (steps.length_m <= 3.0))
        assert np.all(np.diff(steps.t_ms) >= PARAMS.steps.min_interval_ms)


def test_madgwick_with_magnetometer_agrees_with_the_rotation_vector() -> None:
    walk = _walk(TURNING)
    phone = pdr_steps(PdrState(), _imu(walk, ("rv",)), PARAMS)
    ours = pdr_steps(PdrState(), _imu(walk, ("gyr", "mag")), PARAMS)
    common, i, j = np.intersect1d(phone.t_ms, ours.t_ms, return_indices=True)
    assert common.size > 0.9 * phone.t_ms.size
    gap = np.abs((ours.azimuth_rad[j] - phone.azimuth_rad[i] + math.pi) % (2 * math.pi) - math.pi)
    assert np.degrees(np.median(gap)) < 15.0


def test_step_lengths_add_up_to_the_surveyed_walk() -> None:
    walk = _walk()
    steps = pdr_steps(PdrState(), _imu(walk, ("rv",)), PARAMS)
    wp = walk["waypoints"]
    walked = float(np.sum(np.linalg.norm(np.diff(wp[:, 1:], axis=0), axis=1)))
    inside = (steps.t_ms >= wp[0, 0]) & (steps.t_ms <= wp[-1, 0])
    assert 0.8 * walked < float(steps.length_m[inside].sum()) < 1.25 * walked


def test_stale_samples_are_dropped_and_counted_not_reapplied() -> None:
    walk = _walk()
    state = PdrState()
    t0 = walk["acc"][0, 0]
    first = _imu(walk, ("rv", "gyr"), t0, t0 + 2000)
    pdr_steps(state, first, PARAMS)
    again, dropped = drop_stale(state, first)
    assert dropped == first.acc.shape[0] + first.rv.shape[0] + first.gyr.shape[0]
    assert again.acc.shape[0] == 0
    snapshot = state.steps.copy()
    assert pdr_steps(state, again, PARAMS).t_ms.size == 0
    np.testing.assert_array_equal(state.steps, snapshot)
    overlapping = _imu(walk, ("rv", "gyr"), t0 + 1000, t0 + 3000)
    fresh, dropped = drop_stale(state, overlapping)
    assert fresh.acc[0, 0] > first.acc[-1, 0]
    assert dropped > 0


def test_backwards_samples_are_refused_before_touching_the_state() -> None:
    walk = _walk()
    state = PdrState()
    t0 = walk["acc"][0, 0]
    pdr_steps(state, _imu(walk, ("rv",), t0, t0 + 2000), PARAMS)
    before = (state.steps.copy(), state.rv_hold.copy())
    with pytest.raises(ValueError, match="also across batches"):
        pdr_steps(state, _imu(walk, ("rv",), t0 + 1000, t0 + 3000), PARAMS)
    np.testing.assert_array_equal(state.steps, before[0])
    np.testing.assert_array_equal(state.rv_hold, before[1])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"acc": np.zeros((3, 3))}, r"acc: expected an \(N, 4\) array"),
        ({"acc": np.array([[1.0, 0, 0, np.nan]])}, "acc: samples must be finite"),
        ({"acc": np.array([[2.0, 0, 0, 9.8], [1.0, 0, 0, 9.8]])}, "acc: sample times must strictly increase"),
        (
            {"acc": np.zeros((0, 4)), "rv": np.array([[1.0, np.nan, 0, 0, np.nan]])},
            "rv: samples must be finite",
        ),
        ({"acc": np.zeros((0, 4)), "grv": np.zeros((1, 4))}, r"grv: expected an \(N, 5\) array"),
    ],
)
def test_malformed_samples_are_refused(kwargs: dict[str, np.ndarray], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ImuSamples(**kwargs)


def test_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="madgwick_gain"):
        PdrParams(madgwick_gain=-0.1)
