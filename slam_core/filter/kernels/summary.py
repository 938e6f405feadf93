"""Per-user estimates: the weighted mean with its 2x2 covariance, and the paper's maximum-weight particle."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from slam_core.filter.kernels.serial import serial_twin


@njit(cache=True, nogil=True, inline="always")
def _weighted_mean(x: np.ndarray, y: np.ndarray, logw: np.ndarray, u: int) -> tuple[float, float]:
    """The weighted mean of user ``u``'s particles: one sum, in particle order, for every caller."""
    mx = 0.0
    my = 0.0
    for m in range(x.shape[1]):
        w = math.exp(logw[u, m])
        mx += w * x[u, m]
        my += w * y[u, m]
    return mx, my


@njit(cache=True, nogil=True, parallel=True)
def summarise(
    x: np.ndarray, y: np.ndarray, heading: np.ndarray, logw: np.ndarray, users: np.ndarray, out: np.ndarray
) -> None:
    """out[i] = (mean_x, mean_y, cov_xx, cov_xy, cov_yy, best_x, best_y, mean_heading) for users[i].

    The covariance is the weighted sample covariance (a small floor keeps it positive definite when
    every particle sits on one point)."""
    n_particles = x.shape[1]
    for i in prange(users.shape[0]):
        u = users[i]
        mx, my = _weighted_mean(x, y, logw, u)
        sc = 0.0
        ss = 0.0
        best = 0
        cxx = 0.0
        cxy = 0.0
        cyy = 0.0
        for m in range(n_particles):
            w = math.exp(logw[u, m])
            sc += w * math.cos(heading[u, m])
            ss += w * math.sin(heading[u, m])
            if logw[u, m] > logw[u, best]:
                best = m
            dx = x[u, m] - mx
            dy = y[u, m] - my
            cxx += w * dx * dx
            cxy += w * dx * dy
            cyy += w * dy * dy
        out[i, 0] = mx
        out[i, 1] = my
        out[i, 2] = cxx + 1e-6
        out[i, 3] = cxy
        out[i, 4] = cyy + 1e-6
        out[i, 5] = x[u, best]
        out[i, 6] = y[u, best]
        out[i, 7] = math.atan2(ss, sc)


summarise_serial = serial_twin(summarise)


@njit(cache=True, nogil=True, parallel=True)
def weighted_means(
    x: np.ndarray, y: np.ndarray, logw: np.ndarray, users: np.ndarray, out: np.ndarray
) -> None:
    """out[i] = (mean_x, mean_y) for users[i]: ``summarise``'s first two columns, bit for bit (the same
    sums), at a third of its cost: a tracker call predicts the distance of every pair its scans detected,
    and wants no covariance for it."""
    for i in prange(users.shape[0]):
        out[i, 0], out[i, 1] = _weighted_mean(x, y, logw, users[i])


weighted_means_serial = serial_twin(weighted_means)
