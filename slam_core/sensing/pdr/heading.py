"""Walking direction from the gyroscope, referenced to north by a causal average of the absolute azimuth.

Beyond both papers. An absolute azimuth (Android's rotation vector, or Madgwick with a magnetometer) is
pulled by every local magnetic disturbance: on the msindoor walks the rotation vector's yaw wanders
5-35 deg around the gyroscope-integrated yaw within one walk, while the calibrated gyroscope drifts far less.
So the direction of a step is

    azimuth(t) = psi(t) + offset(t),   psi(t) = -integral of the earth-vertical angular rate,
    offset(t)  = circular mean of (absolute azimuth - psi) over the samples up to t,

the mean forgetting with time constant ``tau`` so gyroscope drift over a long session is tracked. Both
are causal, sample by sample with carried state (a walk whole or in one-second batches gives the same
values). Consumers that dead-reckon may also re-rotate what was already walked by the latest offset
(the offset is the best estimate so far of one constant error, see ``BuildingTracker.dead_reckoning``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

# state layout: relative azimuth psi, forgotten sums of sin and cos of (absolute - psi), last sample time
_PSI, _SIN, _COS, _LAST_T = range(4)
STATE_SIZE = 4


@dataclass(frozen=True)
class HeadingParams:
    gyro_heading: bool = True
    """Integrate the gyroscope for the direction and only average the absolute azimuth (False: the absolute
    azimuth per sample, as Android reports it)."""
    offset_tau_s: float = 300.0
    """Memory of the offset average: long against a walk (the offset is one constant error per walk), short
    against a calibrated gyroscope's drift (well under 0.05 deg/s). The msindoor figures move by < 0.05 m
    between 30 s and no forgetting at all."""
    max_gap_ms: float = 500.0
    """A longer gap between samples is not integrated (the rotation during it is unknown)."""

    def __post_init__(self) -> None:
        if not (self.offset_tau_s > 0.0 and self.max_gap_ms > 0.0):
            raise ValueError("offset_tau_s and max_gap_ms must be > 0")


def new_state() -> np.ndarray:
    state = np.zeros(STATE_SIZE)
    state[_PSI] = math.nan
    state[_LAST_T] = math.nan
    return state


def current_offset(state: np.ndarray) -> float:
    """The offset estimate after the samples fed so far (NaN before any absolute azimuth)."""
    s, c = state[_SIN], state[_COS]
    return math.atan2(s, c) if s != 0.0 or c != 0.0 else math.nan


@njit(cache=True, nogil=True)
def _integrate(
    state: np.ndarray,
    t_ms: np.ndarray,
    absolute: np.ndarray,
    rate_up: np.ndarray,
    tau_ms: float,
    max_gap_ms: float,
    out_psi: np.ndarray,
    out_offset: np.ndarray,
) -> None:
    for i in range(t_ms.shape[0]):
        t = t_ms[i]
        last = state[_LAST_T]
        dt = t - last if not math.isnan(last) else math.inf
        if not math.isnan(rate_up[i]):
            if math.isnan(state[_PSI]):
                state[_PSI] = 0.0
            elif dt <= max_gap_ms:
                state[_PSI] -= rate_up[i] * dt * 1e-3  # counter-clockwise rate, clockwise azimuth
        psi = state[_PSI]
        if not math.isnan(absolute[i]) and not math.isnan(psi):
            keep = math.exp(-dt / tau_ms) if dt < math.inf else 0.0
            d = absolute[i] - psi
            state[_SIN] = state[_SIN] * keep + math.sin(d)
            state[_COS] = state[_COS] * keep + math.cos(d)
        state[_LAST_T] = t
        out_psi[i] = psi
        s, c = state[_SIN], state[_COS]
        out_offset[i] = math.atan2(s, c) if s != 0.0 or c != 0.0 else math.nan


def gyro_heading(
    state: np.ndarray, t_ms: np.ndarray, absolute: np.ndarray, rate_up: np.ndarray, params: HeadingParams
) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: the gyroscope-integrated relative azimuth psi (NaN until the first gyroscope sample) and
    the offset that references it to north (NaN until psi and an absolute azimuth coexist). ``absolute``
    and ``rate_up`` (counter-clockwise earth-vertical angular rate, rad/s) are NaN where unknown; ``state``
    (from ``new_state``) is updated in place."""
    t_ms = np.ascontiguousarray(t_ms, dtype=np.float64)
    absolute = np.ascontiguousarray(absolute, dtype=np.float64)
    rate_up = np.ascontiguousarray(rate_up, dtype=np.float64)
    if not (t_ms.shape == absolute.shape == rate_up.shape and t_ms.ndim == 1):
        raise ValueError("t_ms, absolute and rate_up must be 1-D arrays of the same length")
    if t_ms.size and (
        np.any(np.diff(t_ms) <= 0) or (not math.isnan(state[_LAST_T]) and t_ms[0] <= state[_LAST_T])
    ):
        raise ValueError("sample times must strictly increase, also across batches")
    psi = np.empty(t_ms.size)
    offset = np.empty(t_ms.size)
    _integrate(state, t_ms, absolute, rate_up, params.offset_tau_s * 1e3, params.max_gap_ms, psi, offset)
    return psi, offset


def vertical_rate(gyr: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Earth-vertical (counter-clockwise about up) component of phone-frame angular rates (N, 3) for
    [w, x, y, z] quaternions (N, 4) rotating the phone frame into east-north-up."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rate: np.ndarray = (
        2.0 * (x * z - w * y) * gyr[:, 0]
        + 2.0 * (y * z + w * x) * gyr[:, 1]
        + (1.0 - 2.0 * (x * x + y * y)) * gyr[:, 2]
    )
    return rate


def with_final_offset(azimuth: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Offline use (a map built after the walk): each step's azimuth re-referenced by the walk's last north
    offset, the estimate that has seen the most of the walk. Steps without an offset are returned as
    they are; a walk without any keeps its azimuths."""
    finite = np.isfinite(offset)
    if not finite.any():
        return azimuth.copy()
    final = offset[finite][-1]
    turned: np.ndarray = np.where(finite, azimuth - offset + final, azimuth)
    return (turned + math.pi) % (2 * math.pi) - math.pi
