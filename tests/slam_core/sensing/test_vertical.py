"""Floor changes from the barometer on synthetic rides: elevators, stairs and escalators told apart, weather
drift and door transients ignored, batch-split invariance, and every error path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.sensing.vertical import (
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
    from slam_core.sensing.detectors import DetectorParams
    from slam_core.sensing.front_end import FrontEnd, RadioArrays
    from slam_core.sensing.pdr.online import ImuSamples, PdrParams

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


# ----------------------------------------------------------------- lift rides from the accelerometer


def _standing_ride(
    rise_sign: float, seed: int = 0, accel: float = 0.8, cruise_s: float = 5.0, walk_after: bool = True
) -> tuple[np.ndarray, np.ndarray, float]:
    """50 Hz accelerometer (phone held at a tilt, 0.04 m/s^2 noise, a 1 % scale error) of a user who walks
    in, stands 6 s, rides (accel for 1.5 s, cruise, decel 1.5 s), stands 2 s, walks out; step times; the
    ride's end."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 40.0, 0.02)
    start = 10.0
    a = np.zeros(t.size)
    a[(t >= start) & (t < start + 1.5)] = accel
    end_cruise = start + 1.5 + cruise_s
    a[(t >= end_cruise) & (t < end_cruise + 1.5)] = -accel
    a *= rise_sign
    magnitude = 1.01 * (GRAVITY + a) + rng.normal(0.0, 0.04, t.size)
    tilt = np.radians(35.0)
    acc = np.column_stack(
        [T0 + 1e3 * t, np.zeros(t.size), magnitude * np.sin(tilt), magnitude * np.cos(tilt)]
    )
    steps = np.arange(0.0, 4.0, 0.55)
    ride_end = end_cruise + 1.5
    if walk_after:
        steps = np.concatenate([steps, np.arange(ride_end + 2.0, 40.0, 0.55)])
    return acc, (T0 + 1e3 * steps).astype(np.int64), T0 + 1e3 * ride_end


GRAVITY = 9.80665


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_lift_ride_is_found_from_the_accelerometer_while_standing(sign: float) -> None:
    from slam_core.sensing.lift import LiftParams, detect_lift_rides, new_state

    acc, steps, end = _standing_ride(sign)
    ride_t, rise = detect_lift_rides(new_state(), LiftParams(), acc, steps)
    assert ride_t.size == 1
    assert abs(int(ride_t[0]) - end) < 1_500
    assert np.sign(rise[0]) == sign
    assert 4.0 < abs(rise[0]) < 11.0  # 1.2 m/s for 6.5 s: 7.8 m, integrated from a biased accelerometer


def test_standing_still_or_walking_is_no_lift_ride() -> None:
    from slam_core.sensing.lift import LiftParams, detect_lift_rides, new_state

    standing, steps, _ = _standing_ride(1.0, accel=0.0)
    assert detect_lift_rides(new_state(), LiftParams(), standing, steps)[0].size == 0
    acc, _, _ = _standing_ride(1.0)
    walking = (T0 + 1e3 * np.arange(0.0, 40.0, 0.55)).astype(np.int64)  # the same motion, but walking
    assert detect_lift_rides(new_state(), LiftParams(), acc, walking)[0].size == 0
    bump, steps, _ = _standing_ride(1.0, cruise_s=0.0, accel=0.3)  # sitting down, a short sway
    assert detect_lift_rides(new_state(), LiftParams(), bump, steps)[0].size == 0


def test_lift_rides_in_one_second_batches_match_the_whole_stream() -> None:
    from slam_core.sensing.lift import LiftParams, detect_lift_rides, new_state

    acc, steps, _ = _standing_ride(-1.0, seed=5)
    whole = detect_lift_rides(new_state(), LiftParams(), acc, steps)
    state = new_state()
    parts = []
    for start in np.arange(acc[0, 0], acc[-1, 0] + 1, 1000.0):
        rows = acc[(acc[:, 0] >= start) & (acc[:, 0] < start + 1000.0)]
        parts.append(
            detect_lift_rides(state, LiftParams(), rows, steps[(steps >= start) & (steps < start + 1000)])
        )
    np.testing.assert_array_equal(np.concatenate([p[0] for p in parts]), whole[0])
    np.testing.assert_allclose(np.concatenate([p[1] for p in parts]), whole[1], rtol=1e-12)
    with pytest.raises(ValueError, match="across batches"):
        detect_lift_rides(state, LiftParams(), acc[:5], np.zeros(0, np.int64))
    with pytest.raises(ValueError, match="finite"):
        detect_lift_rides(new_state(), LiftParams(), np.array([[T0, math.nan, 0.0, 9.8]]), np.zeros(0))
    with pytest.raises(ValueError, match="bias_s > lowpass_s"):
        LiftParams(bias_s=0.1)


def test_front_end_uses_the_accelerometer_only_without_a_barometer() -> None:
    from slam_core.sensing.detectors import DetectorParams
    from slam_core.sensing.front_end import FrontEnd, RadioArrays
    from slam_core.sensing.pdr.online import ImuSamples, PdrParams

    acc, _, end = _standing_ride(1.0, walk_after=False)
    radio = RadioArrays(
        np.zeros(0, np.int64), np.zeros(1, np.int64), (), np.zeros(0), np.zeros(0, np.int64),
        np.zeros(0, np.int64), (), np.zeros(0),
    )  # fmt: skip
    front = FrontEnd(PdrParams(), DetectorParams())
    out = front.process("u", ImuSamples(acc=acc), radio)
    assert out.anchors.type_index.tolist() == [0]
    assert abs(int(out.anchors.t_ms[0]) - end) < 1_500
    # a phone with a barometer: the barometer decides (a flat pressure: no ride)
    flat = np.column_stack([acc[::10, 0], np.full(acc[::10].shape[0], 1000.0)])
    out = FrontEnd(PdrParams(), DetectorParams()).process("v", ImuSamples(acc=acc, pressure=flat), radio)
    assert out.anchors.t_ms.size == 0
