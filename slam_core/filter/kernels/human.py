"""Human anchors (DynamicSLAM Algorithm 1, Eq. 9-14): refine a user's particles from a relative distance to a
peer summarised by its cloud's mean and covariance, then weight them by the encounter likelihood."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from slam_core.filter.kernels.linalg2 import sample2
from slam_core.filter.kernels.rng import normal
from slam_core.filter.kernels.serial import serial_twin
from slam_core.filter.kernels.weights import finish_observation

CTRL_FLOOR_M2 = 1e-4


@njit(cache=True, nogil=True, inline="always")
def _range_jacobian(px: float, py: float, bx: float, by: float) -> tuple[float, float, float]:
    """h = ||p - b|| (Eq. 9) and its gradient with respect to p (a unit vector)."""
    dx = px - bx
    dy = py - by
    h = math.sqrt(dx * dx + dy * dy)
    if h < 1e-9:
        return 0.0, 1.0, 0.0  # the direction is undefined at zero range: pick one consistently
    return h, dx / h, dy / h


@njit(cache=True, nogil=True)
def refine_one(
    sx: float,
    sy: float,
    bx: float,
    by: float,
    b_xx: float,
    b_xy: float,
    b_yy: float,
    z: float,
    r: float,
    p_xx: float,
    p_xy: float,
    p_yy: float,
    iterative: bool,
    beta: float,
    max_iterations: int,
) -> tuple[float, float, float, float, float, int]:
    """Mean and covariance of the proposal for one particle (Eq. 10-13).

    One-shot sampling linearises once at the predicted position (Eq. 10). Iterative sampling repeats the
    update, relinearising at the latest mean (iterated EKF), until successive means differ by less than beta.
    Returns (mu_x, mu_y, cov_xx, cov_xy, cov_yy, iterations).
    """
    det_p = p_xx * p_yy - p_xy * p_xy
    pi_xx = p_yy / det_p  # P^-1
    pi_xy = -p_xy / det_p
    pi_yy = p_xx / det_p
    mx = sx
    my = sy
    c_xx = p_xx
    c_xy = p_xy
    c_yy = p_yy
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        h, jx, jy = _range_jacobian(mx, my, bx, by)
        # Eq. 12: Q = J_b Sigma_b J_b^T + R, with J_b = -J
        q = jx * jx * b_xx + 2.0 * jx * jy * b_xy + jy * jy * b_yy + r
        # Eq. 11: Sigma = [J^T Q^-1 J + P^-1]^-1
        a_xx = jx * jx / q + pi_xx
        a_xy = jx * jy / q + pi_xy
        a_yy = jy * jy / q + pi_yy
        det_a = a_xx * a_yy - a_xy * a_xy
        c_xx = a_yy / det_a
        c_xy = -a_xy / det_a
        c_yy = a_xx / det_a
        # Eq. 13: K = Sigma J^T Q^-1
        kx = (c_xx * jx + c_xy * jy) / q
        ky = (c_xy * jx + c_yy * jy) / q
        # Eq. 10 (and its iterated form, linearised at the current mean)
        innovation = z - h - (jx * (sx - mx) + jy * (sy - my))
        nx = sx + kx * innovation
        ny = sy + ky * innovation
        moved = math.sqrt((nx - mx) ** 2 + (ny - my) ** 2)
        mx = nx
        my = ny
        if not iterative or moved < beta:
            break
    return mx, my, c_xx, c_xy, c_yy, iterations


@njit(cache=True, nogil=True, parallel=True)
def human_anchor_update(
    x: np.ndarray,
    y: np.ndarray,
    logw: np.ndarray,
    ctrl_cov: np.ndarray,
    rng_key: np.ndarray,
    rng_ctr: np.ndarray,
    users: np.ndarray,
    peer_mean: np.ndarray,
    peer_cov: np.ndarray,
    distance: np.ndarray,
    distance_var: np.ndarray,
    iterative: bool,
    beta: float,
    max_iterations: int,
    outlier_probability: float,
    max_range: float,
    degenerate: np.ndarray,
) -> None:
    """For each i, update user ``users[i]`` with peer summary (``peer_mean[i]``, ``peer_cov[i]``), measured
    distance ``distance[i]`` and its variance R. Users must be distinct within one call.

    Weights: the paper leaves them implicit; here each particle is weighted by the mixture likelihood
    (1 - eps) N(z; h(s_hat), J P J^T + Q) + eps / max_range, evaluated at its predicted position (the
    FastSLAM 2.0 marginal of the proposal), so a wrong encounter cannot wipe out the cloud.
    """
    n_particles = x.shape[1]
    log_eps = math.log(outlier_probability / max_range) if outlier_probability > 0.0 else -np.inf
    log_keep = math.log(1.0 - outlier_probability)
    for i in prange(users.shape[0]):
        u = users[i]
        key = rng_key[u]
        p_xx = ctrl_cov[u, 0] + CTRL_FLOOR_M2
        p_xy = ctrl_cov[u, 1]
        p_yy = ctrl_cov[u, 2] + CTRL_FLOOR_M2
        bx = peer_mean[i, 0]
        by = peer_mean[i, 1]
        b_xx = peer_cov[i, 0]
        b_xy = peer_cov[i, 1]
        b_yy = peer_cov[i, 2]
        z = distance[i]
        r = distance_var[i]
        for m in range(n_particles):
            sx = x[u, m]
            sy = y[u, m]
            h, jx, jy = _range_jacobian(sx, sy, bx, by)
            q = jx * jx * b_xx + 2.0 * jx * jy * b_xy + jy * jy * b_yy + r
            s_var = jx * jx * p_xx + 2.0 * jx * jy * p_xy + jy * jy * p_yy + q
            innovation = z - h
            log_gauss = -0.5 * math.log(2.0 * math.pi * s_var) - 0.5 * innovation * innovation / s_var
            a = log_keep + log_gauss
            mx_ = max(a, log_eps)
            logw[u, m] += mx_ + math.log(math.exp(a - mx_) + math.exp(log_eps - mx_))
            mx, my, c_xx, c_xy, c_yy, _ = refine_one(
                sx, sy, bx, by, b_xx, b_xy, b_yy, z, r, p_xx, p_xy, p_yy, iterative, beta, max_iterations
            )
            n1 = normal(key, rng_ctr, u)
            n2 = normal(key, rng_ctr, u)
            x[u, m], y[u, m] = sample2(mx, my, c_xx, c_xy, c_yy, n1, n2)  # Eq. 14
        finish_observation(logw, ctrl_cov, degenerate, u)


human_anchor_update_serial = serial_twin(human_anchor_update)
