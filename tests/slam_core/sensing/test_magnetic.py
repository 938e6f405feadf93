"""Magnetic anomalies from the magnetometer's magnitude: a local disturbance is reported once at its peak,
noise and a new level of the field are not anomalies, batch-split invariance, every error path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.sensing.magnetic import MagneticParams, MagneticState, detect_magnetic_anomalies

PARAMS = MagneticParams(enabled=True)
T0 = 1_700_000_000_000


def _walk(bumps: list[tuple[float, float]], step_at: float | None = None, seed: int = 0) -> np.ndarray:
    """60 s of 50 Hz magnetometer rows (phone turning slowly, 45 uT field, 0.5 uT noise) with Gaussian
    bumps (centre s, height uT, 1 s wide) and optionally a lasting step of +20 uT at ``step_at``."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 60.0, 0.02)
    magnitude = 45.0 + rng.normal(0.0, 0.5, t.size)
    for centre, height in bumps:
        magnitude += height * np.exp(-0.5 * ((t - centre) / 0.5) ** 2)
    if step_at is not None:
        magnitude += np.where(t > step_at, 20.0, 0.0)
    angle = 0.05 * t
    direction = np.column_stack([np.cos(angle) * 0.6, np.sin(angle) * 0.6, np.full(t.size, 0.8)])
    return np.column_stack([T0 + 1e3 * t, magnitude[:, None] * direction])


def test_each_disturbance_is_reported_once_at_its_peak() -> None:
    rows = _walk([(20.0, 25.0), (40.0, -22.0)])
    events = detect_magnetic_anomalies(MagneticState(), PARAMS, rows)
    assert len(events) == 2
    for (report, peak), centre in zip(events, (20.0, 40.0), strict=True):
        assert abs(peak - (T0 + 1e3 * centre)) < 700  # the smoothing delays the peak a little
        assert 0 < report - peak < 2_000


def test_noise_weak_bumps_and_a_new_field_level_are_not_anomalies() -> None:
    assert detect_magnetic_anomalies(MagneticState(), PARAMS, _walk([(30.0, 6.0)])) == []
    assert detect_magnetic_anomalies(MagneticState(), PARAMS, _walk([], step_at=30.0)) == []


def test_one_second_batches_give_the_anomalies_of_the_whole_stream() -> None:
    rows = _walk([(10.0, 30.0), (25.0, -22.0), (50.0, 18.0)], seed=3)
    whole = detect_magnetic_anomalies(MagneticState(), PARAMS, rows)
    state = MagneticState()
    batched = []
    for start in np.arange(rows[0, 0], rows[-1, 0] + 1, 1000.0):
        batched += detect_magnetic_anomalies(
            state, PARAMS, rows[(rows[:, 0] >= start) & (rows[:, 0] < start + 1000.0)]
        )
    assert len(whole) == 3
    assert batched == whole


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        (np.array([[T0, math.nan, 0.0, 40.0]]), "finite"),
        (np.array([[T0, 0.0, 0.0, 40.0], [T0, 0.0, 0.0, 40.0]]), "strictly increase"),
    ],
)
def test_malformed_samples_are_refused_untouched(rows: np.ndarray, message: str) -> None:
    state = MagneticState()
    with pytest.raises(ValueError, match=message):
        detect_magnetic_anomalies(state, PARAMS, rows)
    assert state == MagneticState()
    detect_magnetic_anomalies(state, PARAMS, np.array([[T0, 0.0, 0.0, 40.0]]))
    with pytest.raises(ValueError, match="across batches"):
        detect_magnetic_anomalies(state, PARAMS, np.array([[T0, 0.0, 0.0, 40.0]]))


def test_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="peak_drop_ut < anomaly_ut"):
        MagneticParams(peak_drop_ut=20.0)
    assert not MagneticParams().enabled  # off by default: it did not help on the real mall floor


def test_front_end_reports_magnetic_anchors_when_enabled() -> None:
    from dataclasses import replace

    from slam_core.sensing.detectors import DetectorParams
    from slam_core.sensing.front_end import FrontEnd, RadioArrays
    from slam_core.sensing.pdr.online import ImuSamples, PdrParams

    mag = _walk([(20.0, 25.0)])
    acc = np.column_stack([mag[:, 0], np.zeros((mag.shape[0], 2)), np.full(mag.shape[0], 9.80665)])
    radio = RadioArrays(
        np.zeros(0, np.int64), np.zeros(1, np.int64), (), np.zeros(0), np.zeros(0, np.int64),
        np.zeros(0, np.int64), (), np.zeros(0),
    )  # fmt: skip
    on = DetectorParams(magnetic=replace(PARAMS, enabled=True))
    for params, expected in ((on, [PARAMS.type_index]), (DetectorParams(), [])):
        front = FrontEnd(PdrParams(), params)
        out = front.process("u", ImuSamples(acc=acc, mag=mag), radio)
        assert out.anchors.type_index.tolist() == expected
        assert front.fired["magnetic"] == len(expected)
