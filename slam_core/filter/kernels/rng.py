"""Counter-based random numbers: one stream per user, ``(key, counter) -> 64 random bits`` (SplitMix64).

A user's draws depend only on its key and counter, never on which thread runs it, so a batch kernel under
``prange`` gives bit-identical results on 1 or 2 threads. ``slam_core.filter.reference`` reimplements the same
streams in NumPy so the textbook filter consumes exactly the same numbers (the kernels' oracle).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_TWO_POW_53 = 1.0 / 9007199254740992.0


@njit(cache=True, nogil=True, inline="always")
def splitmix64(x: np.uint64) -> np.uint64:
    z = x + _GOLDEN
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True, nogil=True, inline="always")
def random_bits(key: np.uint64, counter: np.uint64) -> np.uint64:
    return splitmix64(splitmix64(counter) ^ key)


@njit(cache=True, nogil=True, inline="always")
def uniform(key: np.uint64, counters: np.ndarray, user: int) -> float:
    """U(0, 1), never exactly 0; advances the user's counter by one."""
    c = counters[user]
    counters[user] = c + np.uint64(1)
    return (float(random_bits(key, c) >> _S11) + 0.5) * _TWO_POW_53


# Acklam's rational approximation of the inverse normal CDF (relative error < 1.2e-9): one uniform per
# normal, only multiply-adds in the central 95 %, a log and a sqrt in the tails. Box-Muller (a log, a sqrt
# and a cosine per draw) made the motion update three times slower.
_A = (
    -3.969683028665376e01,
    2.209460984245205e02,
    -2.759285104469687e02,
    1.383577518672690e02,
    -3.066479806614716e01,
    2.506628277459239e00,
)
_B = (
    -5.447609879822406e01,
    1.615858368580409e02,
    -1.556989798598866e02,
    6.680131188771972e01,
    -1.328068155288572e01,
)
_C = (
    -7.784894002430293e-03,
    -3.223964580411365e-01,
    -2.400758277161838e00,
    -2.549732539343734e00,
    4.374664141464968e00,
    2.938163982698783e00,
)
_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e00, 3.754408661907416e00)
_P_LOW = 0.02425


@njit(cache=True, nogil=True, inline="always")
def inverse_normal_cdf(p: float) -> float:
    if p < _P_LOW:
        q = math.sqrt(-2.0 * math.log(p))
        return (((((_C[0] * q + _C[1]) * q + _C[2]) * q + _C[3]) * q + _C[4]) * q + _C[5]) / (
            (((_D[0] * q + _D[1]) * q + _D[2]) * q + _D[3]) * q + 1.0
        )
    if p > 1.0 - _P_LOW:
        q = math.sqrt(-2.0 * math.log(1.0 - p))
        return -(((((_C[0] * q + _C[1]) * q + _C[2]) * q + _C[3]) * q + _C[4]) * q + _C[5]) / (
            (((_D[0] * q + _D[1]) * q + _D[2]) * q + _D[3]) * q + 1.0
        )
    q = p - 0.5
    r = q * q
    return (
        (((((_A[0] * r + _A[1]) * r + _A[2]) * r + _A[3]) * r + _A[4]) * r + _A[5])
        * q
        / (((((_B[0] * r + _B[1]) * r + _B[2]) * r + _B[3]) * r + _B[4]) * r + 1.0)
    )


@njit(cache=True, nogil=True, inline="always")
def normal(key: np.uint64, counters: np.ndarray, user: int) -> float:
    """N(0, 1) from one uniform by the inverse CDF."""
    return inverse_normal_cdf(uniform(key, counters, user))


@njit(cache=True, nogil=True, inline="always")
def normal_at(key: np.uint64, counter: np.uint64) -> float:
    """The normal that ``normal`` draws at this counter value, for loops that keep the counter local
    (a counter in memory, written at every draw, serialised the motion loop)."""
    return inverse_normal_cdf((float(random_bits(key, counter) >> _S11) + 0.5) * _TWO_POW_53)
