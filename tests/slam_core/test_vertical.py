"""Floor changes from the barometer on synthetic rides: elevators, stairs and escalators told apart, weather
drift and door transients ignored, batch-split invariance, and every error path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.vertical import (
    VerticalParams,
    VerticalState,
    detect_floor_changes,
    pressure_height,
)

PARAMS = VerticalParams()
T0 = 1_700_000_000_000


def _pressure(height: np.ndarray) -> np.ndarray:
    return 1013.25 * (1.0 - height / 44_330.77) ** (1.0 / 0.190263)


def _ride(
    rise_m: float,
    speed_mps: float,
    walking: bool,
    seed: int = 0,
    before_s: float = 20.0,
    after_s: float = 20.0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """10 Hz pressure (rows t_ms, hPa) of standing ``before_s``, moving ``rise_m`` at ``speed_mps``, standing
    ``after_s``; the step times (1.8 Hz while walking on the stairs, also before and after the ride) and
    the arrival time."""
    rng = np.random.default_rng(seed)
    ride_s = abs(rise_m) / speed_mps
    t = np.arange(0.0, before_s + ride_s + after_s, 0.1)
    height = 40.0 + rise_m * np.clip((t - before_s) / ride_s, 0.0, 1.0)
    hpa = _pressure(height) + rng.normal(0.0, 0.012, t.size)  # ~0.1 m of barometer noise
    steps = np.arange(0.0, t[-1], 1 / 1.8)
    if not walking:  # walks to the lift or escalator and away from it, stands during the ride
        steps = steps[(steps < before_s - 3.0) | (steps > before_s + ride_s + 1.0)]
    arrival = T0 + 1e3 * (before_s + ride_s)
    return np.column_stack([T0 + 1e3 * t, hpa]), (T0 + 1e3 * steps).astype(np.int64), arrival


@pytest.mark.parametrize(
    ("rise", "speed", "walking", "kind"),
    [
        (10.5, 1.6, False, PARAMS.elevator_type),  # three storeys up by lift
        (-3.5, 1.0, False, PARAMS.elevator_type),  # one down
        (4.0, 0.3, True, PARAMS.stairs_type),
        (-4.0, 0.4, True, PARAMS.stairs_type),
        (5.0, 0.25, False, PARAMS.escalator_type),
    ],
)
def test_rides_are_detected_once_with_their_kind_and_arrival(
    rise: float, speed: float, walking: bool, kind: int
) -> None:
    pressure, steps, arrival = _ride(rise, speed, walking)
    events = detect_floor_changes(VerticalState(), PARAMS, pressure, steps)
    assert len(events) == 1
    event = events[0]
    assert event.type_index == kind
    assert abs(event.change_m - rise) < 0.5
    assert abs(event.observed_t_ms - arrival) < 2_500
    # reported once steady for settle_ms, a little later than that after the smoothed arrival
    assert (
        event.observed_t_ms + PARAMS.settle_ms <= event.t_ms <= event.observed_t_ms + PARAMS.settle_ms + 4_000
    )


def test_weather_drift_noise_and_door_transients_are_not_floor_changes() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 3600.0, 0.1)  # an hour on one floor
    hpa = 1000.0 - t / 3600.0 + rng.normal(0.0, 0.012, t.size)  # -1 hPa in the hour (~8 m)
    door = (t % 600.0 > 300.0) & (t % 600.0 < 302.0)
    hpa[door] += 0.15  # a door or the ventilation, every ten minutes, for two seconds
    events = detect_floor_changes(
        VerticalState(), PARAMS, np.column_stack([T0 + 1e3 * t, hpa]), np.zeros(0, np.int64)
    )
    assert events == []


def test_one_second_batches_give_the_events_of_the_whole_stream() -> None:
    parts = [_ride(10.5, 1.6, False, seed=2), _ride(-4.0, 0.35, True, seed=3)]
    offset = parts[0][0][-1, 0] - T0 + 100.0
    pressure = np.vstack([parts[0][0], parts[1][0] + [offset, 0.0]])
    pressure[parts[0][0].shape[0] :, 1] += parts[0][0][-1, 1] - parts[1][0][0, 1]  # continue from the top
    steps = np.concatenate([parts[0][1], parts[1][1] + int(offset)])
    whole = detect_floor_changes(VerticalState(), PARAMS, pressure, steps)
    state = VerticalState()
    batched = []
    for start in np.arange(pressure[0, 0], pressure[-1, 0] + 1, 1000.0):
        rows = pressure[(pressure[:, 0] >= start) & (pressure[:, 0] < start + 1000.0)]
        mine = steps[(steps >= start) & (steps < start + 1000.0)]
        batched += detect_floor_changes(state, PARAMS, rows, mine)
    assert [e.type_index for e in whole] == [PARAMS.elevator_type, PARAMS.stairs_type]
    assert batched == whole


def test_a_gap_restarts_without_inventing_a_ride() -> None:
    state = VerticalState()
    first = np.column_stack([T0 + 100.0 * np.arange(50), _pressure(np.full(50, 40.0))])
    later = np.column_stack([T0 + 60_000 + 100.0 * np.arange(50), _pressure(np.full(50, 52.0))])
    assert detect_floor_changes(state, PARAMS, first, np.zeros(0, np.int64)) == []
    assert detect_floor_changes(state, PARAMS, later, np.zeros(0, np.int64)) == []


def test_pressure_height_is_the_standard_atmosphere() -> None:
    assert abs(float(pressure_height(np.array([1013.25]))[0])) < 1e-9
    # near sea level one hPa is about 8.3 m
    assert 8.0 < float(pressure_height(np.array([1000.0]))[0] - pressure_height(np.array([1001.0]))[0]) < 8.6


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        (np.array([[T0, math.nan]]), "finite"),
        (np.array([[T0, 50.0]]), "300-1100"),
        (np.array([[T0, 1000.0], [T0, 1000.0]]), "strictly increase"),
    ],
)
def test_malformed_pressure_is_refused_untouched(rows: np.ndarray, message: str) -> None:
    state = VerticalState()
    with pytest.raises(ValueError, match=message):
        detect_floor_changes(state, PARAMS, rows, np.zeros(0, np.int64))
    assert state == VerticalState()


def test_samples_before_the_last_batch_are_refused() -> None:
    state = VerticalState()
    detect_floor_changes(state, PARAMS, np.array([[T0, 1000.0], [T0 + 100, 1000.0]]), np.zeros(0, np.int64))
    with pytest.raises(ValueError, match="across batches"):
        detect_floor_changes(state, PARAMS, np.array([[T0 + 100, 1000.0]]), np.zeros(0, np.int64))


def test_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="settle_m < onset_m"):
        VerticalParams(onset_m=3.0)


def test_front_end_reports_a_lift_ride_of_a_raw_imu_phone() -> None:
    from slam_core.detectors import DetectorParams
    from slam_core.front_end import FrontEnd, RadioArrays
    from slam_core.pdr.frontend import ImuSamples, PdrParams

    pressure, _, arrival = _ride(7.0, 1.5, walking=False)
    t = np.arange(pressure[0, 0], pressure[-1, 0], 20.0)
    acc = np.column_stack([t, np.zeros(t.size), np.zeros(t.size), np.full(t.size, 9.80665)])  # standing
    radio = RadioArrays(
        np.zeros(0, np.int64), np.zeros(1, np.int64), (), np.zeros(0), np.zeros(0, np.int64),
        np.zeros(0, np.int64), (), np.zeros(0),
    )  # fmt: skip
    front = FrontEnd(PdrParams(), DetectorParams())
    out = front.process("u", ImuSamples(acc=acc, pressure=pressure), radio)
    assert out.anchors.type_index.tolist() == [PARAMS.elevator_type]
    assert abs(int(out.anchors.observed_t_ms[0]) - arrival) < 2_500
    assert front.fired["elevator"] == 1
    # the same batch again: every sample is stale, dropped and counted, and nothing is reported twice
    again = front.process("u", ImuSamples(acc=acc, pressure=pressure), radio)
    assert again.anchors.t_ms.size == 0
    assert again.imu_samples_dropped == acc.shape[0] + pressure.shape[0]
