"""Causal step detection with Weinberg step length, sample by sample with carried state.

Vertical acceleration (gravity removed) is low-passed by a second-order Butterworth section; a step is a
peak above ``peak_threshold`` followed by a fall of at least ``hysteresis``, at least ``min_interval_ms``
after the previous step. Its length is Weinberg's K (a_max - a_min)^(1/4) over the samples since the
previous step. The first peak after a standstill (more than ``max_interval_ms`` since the last peak) starts
a walk and is not a step: gait initiation shifts the weight onto the stance leg before the first foot
leaves, a small bump 0.7-1.4 s ahead of the first heel strike (on the msindoor walks, regressing straight
segments' surveyed lengths on their steps gives such peaks a length of 0.00 +- 0.03 of a step).

The step's direction is the circular mean of the per-sample azimuth from the previous step's peak to this
one's (a single sample's azimuth swings with the gait). All state lives in one float array, so a walk
processed whole or in one-second batches gives the same steps (tested).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

GRAVITY = 9.80665

# state layout
(_Z1, _Z2, _PREV_T, _LAST_STEP_T, _PEAK, _PEAK_T, _ARMED, _WIN_MAX, _WIN_MIN, _SIN, _COS, _SIN_PEAK,
 _COS_PEAK) = range(13)  # fmt: skip
STATE_SIZE = 13


@dataclass(frozen=True)
class StepParams:
    cutoff_hz: float = 2.0
    """Walking cadence is 1.5-2.2 Hz; on the msindoor walks 2 Hz gave the steadiest Weinberg swing (the
    per-walk length-ratio spread fell from 0.115 at 3 Hz to 0.090)."""
    sample_hz: float = 50.0
    """Design rate of the low-pass filter; phones deliver about this (the msindoor phone: 50 Hz)."""
    peak_threshold: float = 0.6
    """m/s^2 of filtered vertical acceleration."""
    hysteresis: float = 0.4
    min_interval_ms: float = 300.0
    max_interval_ms: float = 1000.0
    """A longer gap between peaks is a standstill (the slowest natural cadence is about one step a second):
    the next peak starts a new walk."""
    weinberg_k: float = 0.42
    """Weinberg's constant for (a_max - a_min) of the 2 Hz-filtered vertical acceleration in m/s^2 -> metres.
    0.42 made the median walk's step sum equal its surveyed length on the shared msindoor floor (one phone
    model, held flat): a property of the filter and the gait, not of the floor. Without the walk-start peaks
    the refit gives 0.435, well inside the per-walk spread (log sd 0.09), and the waypoint error is flat
    from 0.40 to 0.435, so it stays. ``crowdslam calibrate`` refits it; the bias-scale motion model then
    learns each user's own scale."""

    def butterworth(self) -> tuple[float, float, float, float, float]:
        """Second-order low-pass coefficients (b0, b1, b2, a1, a2), bilinear transform."""
        k = math.tan(math.pi * self.cutoff_hz / self.sample_hz)
        norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
        b0 = k * k * norm
        return b0, 2.0 * b0, b0, 2.0 * (k * k - 1.0) * norm, (1.0 - math.sqrt(2.0) * k + k * k) * norm


def new_state() -> np.ndarray:
    state = np.zeros(STATE_SIZE)
    state[_PREV_T] = math.nan
    state[_LAST_STEP_T] = math.nan
    state[_PEAK] = -math.inf
    state[_WIN_MAX] = -math.inf
    state[_WIN_MIN] = math.inf
    return state


# The compiled detector takes its carried state (``new_state``) and parameters as plain arrays and
# scalars, as numba compiles them.
@njit(cache=True, nogil=True)
def _detect(
    state: np.ndarray,
    t_ms: np.ndarray,
    vertical: np.ndarray,
    azimuth: np.ndarray,
    coeffs: np.ndarray,
    peak_threshold: float,
    hysteresis: float,
    min_interval_ms: float,
    max_interval_ms: float,
    weinberg_k: float,
    out_t: np.ndarray,
    out_len: np.ndarray,
    out_azimuth: np.ndarray,
) -> int:
    b0, b1, b2, a1, a2 = coeffs[0], coeffs[1], coeffs[2], coeffs[3], coeffs[4]
    n_steps = 0
    for i in range(t_ms.shape[0]):
        # transposed direct form II, state carried across calls
        v = vertical[i]
        y = b0 * v + state[_Z1]
        state[_Z1] = b1 * v - a1 * y + state[_Z2]
        state[_Z2] = b2 * v - a2 * y
        t = t_ms[i]
        state[_PREV_T] = t
        if y > state[_WIN_MAX]:
            state[_WIN_MAX] = y
        if y < state[_WIN_MIN]:
            state[_WIN_MIN] = y
        if not math.isnan(azimuth[i]):
            state[_SIN] += math.sin(azimuth[i])
            state[_COS] += math.cos(azimuth[i])
        if y > peak_threshold and y > state[_PEAK]:
            state[_PEAK] = y
            state[_PEAK_T] = t
            state[_ARMED] = 1.0
            state[_SIN_PEAK] = state[_SIN]
            state[_COS_PEAK] = state[_COS]
        if state[_ARMED] > 0.0 and y < state[_PEAK] - hysteresis:
            peak_t = state[_PEAK_T]
            last = state[_LAST_STEP_T]
            if math.isnan(last) or peak_t - last >= min_interval_ms:
                if not (math.isnan(last) or peak_t - last > max_interval_ms):
                    out_t[n_steps] = peak_t
                    swing = max(state[_WIN_MAX] - state[_WIN_MIN], 0.0)
                    out_len[n_steps] = weinberg_k * swing**0.25
                    s, c = state[_SIN_PEAK], state[_COS_PEAK]
                    out_azimuth[n_steps] = math.atan2(s, c) if s != 0.0 or c != 0.0 else math.nan
                    n_steps += 1
                # else: the weight shift that starts a walk, not a step
                state[_LAST_STEP_T] = peak_t
                state[_WIN_MAX] = y
                state[_WIN_MIN] = y
            # the samples after the peak belong to the next step
            state[_SIN] -= state[_SIN_PEAK]
            state[_COS] -= state[_COS_PEAK]
            state[_ARMED] = 0.0
            state[_PEAK] = -math.inf
    return n_steps


def detect_steps(
    state: np.ndarray,
    t_ms: np.ndarray,
    vertical_acc: np.ndarray,
    params: StepParams,
    azimuth: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feed samples (ms, vertical acceleration with gravity removed, m/s^2, and optionally each sample's
    azimuth in rad, NaN where unknown); returns the times, lengths and mean azimuths of the steps completed
    in this batch (an azimuth is NaN when none was given).
    ``state`` (from ``new_state``) is updated in place."""
    t_ms = np.ascontiguousarray(t_ms, dtype=np.float64)
    vertical_acc = np.ascontiguousarray(vertical_acc, dtype=np.float64)
    if azimuth is None:
        azimuth = np.full(t_ms.shape, np.nan)
    azimuth = np.ascontiguousarray(azimuth, dtype=np.float64)
    if t_ms.shape != vertical_acc.shape or t_ms.shape != azimuth.shape or t_ms.ndim != 1:
        raise ValueError("t_ms, vertical_acc and azimuth must be 1-D arrays of the same length")
    if not (np.all(np.isfinite(t_ms)) and np.all(np.isfinite(vertical_acc))):
        raise ValueError("samples must be finite")
    if t_ms.size and (
        np.any(np.diff(t_ms) <= 0) or (np.isfinite(state[_PREV_T]) and t_ms[0] <= state[_PREV_T])
    ):
        raise ValueError("sample times must strictly increase, also across batches")
    out_t = np.empty(t_ms.size)
    out_len = np.empty(t_ms.size)
    out_azimuth = np.empty(t_ms.size)
    n = _detect(
        state, t_ms, vertical_acc, azimuth, np.array(params.butterworth()), params.peak_threshold,
        params.hysteresis, params.min_interval_ms, params.max_interval_ms, params.weinberg_k, out_t, out_len,
        out_azimuth,
    )  # fmt: skip
    return out_t[:n].copy(), out_len[:n].copy(), out_azimuth[:n].copy()


def vertical_acceleration(acc: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Earth-frame vertical component of phone-frame accelerations (N, 3), rotated by [w, x, y, z]
    quaternions (N, 4) from the phone frame to east-north-up, minus gravity."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r20 = 2.0 * (x * z - w * y)
    r21 = 2.0 * (y * z + w * x)
    r22 = 1.0 - 2.0 * (x * x + y * y)
    vertical: np.ndarray = r20 * acc[:, 0] + r21 * acc[:, 1] + r22 * acc[:, 2] - GRAVITY
    return vertical
