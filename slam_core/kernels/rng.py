"""Counter-based random numbers: one stream per user, ``(key, counter) -> 64 random bits`` (SplitMix64).

A user's draws depend only on its key and counter, never on which thread runs it, so a batch kernel under
``prange`` gives bit-identical results on 1 or 2 threads. ``slam_core.reference`` reimplements the same
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


@njit(cache=True, nogil=True, inline="always")
def normal(key: np.uint64, counters: np.ndarray, user: int) -> float:
    """N(0, 1) by Box-Muller from two uniforms (the cosine branch only, so each draw costs two counters)."""
    u1 = uniform(key, counters, user)
    u2 = uniform(key, counters, user)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
