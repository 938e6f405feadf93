"""Causal step detection: a synthetic gait, batch-split invariance, error paths, the vertical projection,
and a real walk's step count against its surveyed length."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from slam_core.sensing.pdr.orientation import quaternion_from_rotation_vector
from slam_core.sensing.pdr.steps import StepParams, detect_steps, new_state, vertical_acceleration
from tests.conftest import SAMPLE_FLOOR

pytestmark = pytest.mark.walks

PARAMS = StepParams()
WALKS = SAMPLE_FLOOR / "path_data_files"


def _gait(
    seconds: float = 20.0, cadence_hz: float = 1.8, amplitude: float = 2.5, seed: int = 0
) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = 1.7e12 + np.arange(0.0, seconds * 1000.0, 20.0)
    s = (t - t[0]) / 1000.0
    vertical = amplitude * np.sin(2 * math.pi * cadence_hz * s) + rng.normal(0, 0.15, t.size)
    return t, vertical


def test_one_step_per_gait_cycle_with_constant_length() -> None:
    t, vertical = _gait()
    times, lengths, _ = detect_steps(new_state(), t, vertical, PARAMS)
    assert abs(times.size - (20.0 * 1.8 - 1)) <= 2  # the walk's first peak is not a step
    assert np.all(np.isfinite(lengths))
    assert np.std(lengths) < 0.05 * np.mean(lengths)
    assert np.all(np.diff(times) >= PARAMS.min_interval_ms)


def test_the_peak_that_starts_a_walk_after_a_standstill_is_not_a_step() -> None:
    """Gait initiation: the first peak after standing longer than ``max_interval_ms`` only starts the walk.
    The gait's maxima lie at (k + 1/4) / 1.8 s: eight up to the standstill at 4 s (the last, at 4.03 s,
    cut at its top) and seven in (6, 10) s."""
    t, walking = _gait(seconds=10.0)
    s = (t - t[0]) / 1000.0
    vertical = np.where((s > 4.0) & (s < 6.0), 0.0, walking)
    times, lengths, _ = detect_steps(new_state(), t, vertical, PARAMS)
    resumed = t[0] + 6000.0
    assert (times < resumed).sum() == 7
    assert (times > resumed).sum() == 6
    assert np.all(np.isfinite(lengths))
    # the same gait with a pause shorter than max_interval_ms: one walk, only its first peak dropped
    one_walk = replace(PARAMS, max_interval_ms=5000.0)
    assert (detect_steps(new_state(), t, vertical, one_walk)[0] > resumed).sum() == 7


def test_stronger_steps_are_longer() -> None:
    t, soft = _gait(amplitude=1.5)
    _, hard = _gait(amplitude=4.0)
    soft_len = np.nanmean(detect_steps(new_state(), t, soft, PARAMS)[1])
    hard_len = np.nanmean(detect_steps(new_state(), t, hard, PARAMS)[1])
    assert hard_len > soft_len * (4.0 / 1.5) ** 0.25 * 0.95  # Weinberg: fourth root of the swing


def test_standing_still_gives_no_steps() -> None:
    t = 1.7e12 + np.arange(0.0, 10_000.0, 20.0)
    vertical = np.random.default_rng(1).normal(0, 0.1, t.size)
    assert detect_steps(new_state(), t, vertical, PARAMS)[0].size == 0


def test_a_walk_in_one_second_batches_gives_the_same_steps() -> None:
    t, vertical = _gait(seconds=30.0, seed=3)
    whole = detect_steps(new_state(), t, vertical, PARAMS)
    state = new_state()
    parts_t, parts_len = [], []
    for start in np.arange(t[0], t[-1] + 1, 1000.0):
        sel = (t >= start) & (t < start + 1000.0)
        bt, bl, _ = detect_steps(state, t[sel], vertical[sel], PARAMS)
        parts_t.append(bt)
        parts_len.append(bl)
    np.testing.assert_array_equal(np.concatenate(parts_t), whole[0])
    np.testing.assert_array_equal(np.concatenate(parts_len), whole[1])


@pytest.mark.parametrize(
    ("t", "v", "message"),
    [
        (np.array([1.0, 1.0]), np.zeros(2), "strictly increase"),
        (np.array([1.0, 2.0]), np.array([0.0, np.nan]), "finite"),
        (np.array([1.0, 2.0]), np.zeros(3), "same length"),
    ],
)
def test_bad_samples_are_rejected(t: np.ndarray, v: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        detect_steps(new_state(), t, v, PARAMS)


def test_a_batch_older_than_the_last_one_is_rejected() -> None:
    state = new_state()
    detect_steps(state, np.array([10.0, 20.0]), np.zeros(2), PARAMS)
    with pytest.raises(ValueError, match="across batches"):
        detect_steps(state, np.array([15.0, 30.0]), np.zeros(2), PARAMS)


def test_vertical_projection() -> None:
    flat = np.array([[1.0, 0.0, 0.0, 0.0]])
    assert vertical_acceleration(np.array([[0.0, 0.0, 9.80665]]), flat)[0] == pytest.approx(0.0)
    half = math.radians(90.0) / 2  # phone rolled 90 deg about its y axis: its x axis points down
    rolled = np.array([[math.cos(half), 0.0, math.sin(half), 0.0]])
    assert vertical_acceleration(np.array([[-9.80665 - 1.0, 0.0, 0.0]]), rolled)[0] == pytest.approx(1.0)


def test_real_walk_step_count_matches_its_length() -> None:
    from server.datasets.msindoor import read_trace  # the reader lives at the I/O edge

    trace = read_trace(WALKS / "5dd9fd499191710006b570de.txt")
    acc = trace.streams["accelerometer"]
    rv = trace.streams["rotation_vector"]
    q = quaternion_from_rotation_vector(
        np.column_stack([np.interp(acc[:, 0], rv[:, 0], rv[:, k]) for k in (1, 2, 3)])
    )
    times, lengths, _ = detect_steps(new_state(), acc[:, 0], vertical_acceleration(acc[:, 1:4], q), PARAMS)
    wp = trace.waypoints
    walked = float(np.sum(np.linalg.norm(np.diff(wp[:, 1:], axis=0), axis=1)))
    inside = (times >= wp[0, 0]) & (times <= wp[-1, 0])
    estimated = float(np.nansum(lengths[inside]))
    assert 0.7 * walked < estimated < 1.3 * walked, (walked, estimated, int(inside.sum()))
