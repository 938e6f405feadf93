"""Lift rides from the accelerometer alone, for phones without a barometer (SemanticSLAM's and DynamicSLAM's
elevator anchor: the user stands still while the floor accelerates up or down, cruises, and decelerates).

While the user stands (not two steps within ``still_ms``: the step detector may take a lift's jolt for
one), the accelerometer's magnitude minus gravity is the vertical acceleration whatever the phone's
attitude (the horizontal part is nil). Its resting bias is tracked, the rest is low-passed and integrated
into vertical speed and height; a ride is a speed of at least ``min_speed_mps`` that comes back to rest
having moved at least ``min_rise_m``. A step, a gap or an overlong ride abandons it; a bump that never
builds speed is dropped. Per user, sample by sample with all state in one float array (numba), so a stream
whole or in one-second batches gives the same rides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

GRAVITY = 9.80665

# state layout
(_LAST_T, _ACC, _BIAS, _RIDING, _SPEED, _HEIGHT, _PEAK, _START_T, _CALM_T, _LAST_STEP_T,
 _STILL_SINCE, _PREV_STEP_T) = range(12)  # fmt: skip
STATE_SIZE = 12


@dataclass(frozen=True)
class LiftParams:
    enabled: bool = True
    lowpass_s: float = 0.25
    """Removes the hand's tremor; a lift's acceleration lasts a second or more."""
    bias_s: float = 5.0
    """Memory of the resting bias (the sensor's offset and scale error at 1 g)."""
    still_ms: float = 1_500.0
    """No step for this long: the user stands (a walking step is ~0.5 s)."""
    pulse_mps2: float = 0.2
    """Low-passed acceleration that opens a possible ride (lifts accelerate at 0.5-1.5 m/s^2)."""
    min_speed_mps: float = 0.4
    min_rise_m: float = 2.0
    max_ride_ms: float = 60_000.0
    max_gap_ms: float = 500.0
    type_index: int = 0  # the engine's elevator

    def __post_init__(self) -> None:
        if not (
            self.lowpass_s > 0
            and self.bias_s > self.lowpass_s
            and self.still_ms > 0
            and self.pulse_mps2 > 0
            and self.min_speed_mps > 0
            and self.min_rise_m > 0
            and self.max_ride_ms > 0
            and self.max_gap_ms > 0
        ):
            raise ValueError("lift parameters must be > 0, with bias_s > lowpass_s")


def new_state() -> np.ndarray:
    state = np.zeros(STATE_SIZE)
    state[_LAST_T] = math.nan
    state[_LAST_STEP_T] = -math.inf
    state[_PREV_STEP_T] = -math.inf
    state[_STILL_SINCE] = math.nan
    return state


# The compiled detector takes its carried state (``new_state``) and parameters as plain arrays and
# scalars, as numba compiles them.
@njit(cache=True, nogil=True)
def _rides(
    state: np.ndarray,
    t_ms: np.ndarray,
    magnitude: np.ndarray,
    step_t: np.ndarray,
    lowpass_ms: float,
    bias_ms: float,
    still_ms: float,
    pulse: float,
    min_speed: float,
    min_rise: float,
    max_ride_ms: float,
    max_gap_ms: float,
    out_t: np.ndarray,
    out_rise: np.ndarray,
) -> int:
    n_out = 0
    k = 0
    for i in range(t_ms.shape[0]):
        t = t_ms[i]
        while k < step_t.shape[0] and step_t[k] <= t:
            if step_t[k] > state[_LAST_STEP_T]:
                state[_PREV_STEP_T] = state[_LAST_STEP_T]
                state[_LAST_STEP_T] = step_t[k]
            k += 1
        dt = t - state[_LAST_T] if not math.isnan(state[_LAST_T]) else math.inf
        state[_LAST_T] = t
        a = magnitude[i] - GRAVITY
        if dt > max_gap_ms:  # start, or the stream had a hole: nothing known about the motion
            state[_ACC] = 0.0
            state[_BIAS] = a
            state[_RIDING] = 0.0
            state[_STILL_SINCE] = t
            continue
        walking = t - state[_LAST_STEP_T] < still_ms and state[_LAST_STEP_T] - state[_PREV_STEP_T] < still_ms
        if walking:  # no ride, and the bias is not learnt (a lone "step" is a lift's jolt, not a walk)
            state[_RIDING] = 0.0
            state[_STILL_SINCE] = t
            state[_ACC] = 0.0
            continue
        state[_ACC] += (1.0 - math.exp(-dt / lowpass_ms)) * (a - state[_BIAS] - state[_ACC])
        acc = state[_ACC]
        if state[_RIDING] == 0.0:
            if abs(acc) > pulse and t - state[_STILL_SINCE] >= lowpass_ms * 4.0:
                state[_RIDING] = 1.0
                state[_SPEED] = 0.0
                state[_HEIGHT] = 0.0
                state[_PEAK] = 0.0
                state[_START_T] = t
                state[_CALM_T] = t
            else:
                state[_BIAS] += (1.0 - math.exp(-dt / bias_ms)) * (a - state[_BIAS])
            continue
        state[_SPEED] += acc * dt * 1e-3
        state[_HEIGHT] += state[_SPEED] * dt * 1e-3
        speed = abs(state[_SPEED])
        if speed > state[_PEAK]:
            state[_PEAK] = speed
        if abs(acc) > pulse:
            state[_CALM_T] = t
        calm = t - state[_CALM_T]
        if t - state[_START_T] > max_ride_ms:
            state[_RIDING] = 0.0
        elif state[_PEAK] < min_speed:
            if calm > 2_000.0:  # a bump that built no speed
                state[_RIDING] = 0.0
        elif speed < 0.25 * state[_PEAK] and calm > 0.0:
            state[_RIDING] = 0.0
            if abs(state[_HEIGHT]) >= min_rise:
                out_t[n_out] = t
                out_rise[n_out] = state[_HEIGHT]
                n_out += 1
    return n_out


def detect_lift_rides(
    state: np.ndarray, params: LiftParams, acc: np.ndarray, step_t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Feed one batch of accelerometer rows (t_ms, x, y, z; times strictly increasing, also across batches)
    and the user's step times; returns the times at which rides ended (the user is at the lift's door)
    and their signed rise in metres. ``state`` (from ``new_state``) is updated in place."""
    acc = np.ascontiguousarray(acc, dtype=np.float64).reshape(-1, 4)
    if not np.all(np.isfinite(acc)):
        raise ValueError("acc: samples must be finite")
    if acc.shape[0] > 1 and np.any(np.diff(acc[:, 0]) <= 0):
        raise ValueError("acc: sample times must strictly increase")
    if acc.size and not math.isnan(state[_LAST_T]) and acc[0, 0] <= state[_LAST_T]:
        raise ValueError("acc: sample times must strictly increase, also across batches")
    out_t = np.empty(acc.shape[0])
    out_rise = np.empty(acc.shape[0])
    n = _rides(
        state, np.ascontiguousarray(acc[:, 0]), np.linalg.norm(acc[:, 1:4], axis=1),
        np.sort(np.asarray(step_t, dtype=np.float64)), params.lowpass_s * 1e3, params.bias_s * 1e3,
        params.still_ms, params.pulse_mps2, params.min_speed_mps, params.min_rise_m, params.max_ride_ms,
        params.max_gap_ms, out_t, out_rise,
    )  # fmt: skip
    return out_t[:n].astype(np.int64), out_rise[:n].copy()
