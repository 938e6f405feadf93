"""2x2 symmetric algebra as scalars, covariances stored as (xx, xy, yy)."""

from __future__ import annotations

import math

from numba import njit

LOG_2PI = math.log(2.0 * math.pi)


@njit(cache=True, nogil=True)
def largest_eigenvalue2(a: float, b: float, c: float) -> float:
    """The larger eigenvalue of [[a, b], [b, c]]: a covariance's larger variance."""
    half_gap = 0.5 * (a - c)
    return 0.5 * (a + c) + math.sqrt(half_gap * half_gap + b * b)


@njit(cache=True, nogil=True, inline="always")
def gauss_logpdf2(dx: float, dy: float, a: float, b: float, c: float) -> float:
    """log N((dx, dy); 0, [[a, b], [b, c]])."""
    d = a * c - b * b
    m = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / d
    return -LOG_2PI - 0.5 * math.log(d) - 0.5 * m


@njit(cache=True, nogil=True, inline="always")
def sample2(mx: float, my: float, a: float, b: float, c: float, n1: float, n2: float) -> tuple[float, float]:
    """mean + chol([[a, b], [b, c]]) @ (n1, n2)."""
    l11 = math.sqrt(max(a, 0.0))
    l21 = b / l11 if l11 > 0.0 else 0.0
    l22 = math.sqrt(max(c - l21 * l21, 0.0))
    return mx + l11 * n1, my + l21 * n1 + l22 * n2


@njit(cache=True, nogil=True, inline="always")
def wrap_angle(a: float) -> float:
    """Into [-pi, pi); the loops run at most once for the angles a step produces."""
    while a >= math.pi:
        a -= 2.0 * math.pi
    while a < -math.pi:
        a += 2.0 * math.pi
    return a
