"""Building anchors (DynamicSLAM Algorithm 2 lines 9-20, Eq. 15-17, Algorithm 3), batched over users.

A detection says "the user is at an anchor of detected type f_hat". In the paper's convergence section the
observation is linear: z = mu_n - s with J_n = I, J_s = -I and Q = R + Sigma_n; we use exactly that, with
z = 0 (the user stands at the anchor) and R = detection_sigma^2 I.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from slam_core.filter.kernels.arrays import (
    CTRL_COV,
    LOGW,
    N_DEGENERATE,
    N_MAP_OVERFLOW,
    RNG_CTR,
    RNG_KEY,
    FilterArrays,
    X,
    Y,
    particle_maps,
)
from slam_core.filter.kernels.linalg2 import gauss_logpdf2, sample2
from slam_core.filter.kernels.rng import normal
from slam_core.filter.kernels.serial import serial_twin
from slam_core.filter.kernels.weights import finish_observation

CTRL_FLOOR_M2 = 1e-4
NEW_ANCHOR = -1


@njit(cache=True, nogil=True)
def associate(
    sx: float,
    sy: float,
    map_mu: np.ndarray,
    map_cov: np.ndarray,
    map_type: np.ndarray,
    n_anchors: int,
    detected: int,
    type_posterior: np.ndarray,
    r: float,
    p_xx: float,
    p_xy: float,
    p_yy: float,
    log_p0: float,
) -> tuple[int, float]:
    """Maximum-likelihood anchor for one particle (Algorithm 2 lines 10-17).

    Eq. 15: p_n = N(s - mu_n; 0, Q_n + P) p(f_n | f_hat), Q_n = Sigma_n + R (the proposal's marginal, as in
    FastSLAM 2.0; eta cancels in the argmax). Eq. 16: a new anchor scores p0 p(f_hat | f_hat).
    Returns (index or NEW_ANCHOR, log p of the chosen hypothesis).
    """
    best = NEW_ANCHOR
    best_log = log_p0 + math.log(type_posterior[detected, detected])
    for n in range(n_anchors):
        type_p = type_posterior[map_type[n], detected]
        if type_p <= 0.0:
            continue
        a = map_cov[n, 0] + r + p_xx
        b = map_cov[n, 1] + p_xy
        c = map_cov[n, 2] + r + p_yy
        lp = gauss_logpdf2(sx - map_mu[n, 0], sy - map_mu[n, 1], a, b, c) + math.log(type_p)
        if lp > best_log:
            best_log = lp
            best = n
    return best, best_log


@njit(cache=True, nogil=True)
def _update_user(
    i: int,
    arrays: FilterArrays,
    users: np.ndarray,
    detected_type: np.ndarray,
    anchors: tuple[np.ndarray, float, float],
    used_slot: np.ndarray,
) -> None:
    x, y, logw = arrays[X], arrays[Y], arrays[LOGW]
    map_mu, map_cov, map_type, map_count, map_known, map_crowd_id, map_n = particle_maps(arrays)
    ctrl_cov, rng_key, rng_ctr = arrays[CTRL_COV], arrays[RNG_KEY], arrays[RNG_CTR]
    overflow, degenerate = arrays[N_MAP_OVERFLOW], arrays[N_DEGENERATE]
    type_posterior, detection_sigma, new_anchor_likelihood = anchors
    n_particles = x.shape[1]
    capacity = map_mu.shape[2]
    r = detection_sigma * detection_sigma
    log_p0 = math.log(new_anchor_likelihood)
    u = users[i]
    key = rng_key[u]
    det = detected_type[i]
    p_xx = ctrl_cov[u, 0] + CTRL_FLOOR_M2
    p_xy = ctrl_cov[u, 1]
    p_yy = ctrl_cov[u, 2] + CTRL_FLOOR_M2
    for m in range(n_particles):
        sx = x[u, m]
        sy = y[u, m]
        n_anchors = map_n[u, m]
        best, best_log = associate(
            sx,
            sy,
            map_mu[u, m],
            map_cov[u, m],
            map_type[u, m],
            n_anchors,
            det,
            type_posterior,
            r,
            p_xx,
            p_xy,
            p_yy,
            log_p0,
        )
        n1 = normal(key, rng_ctr, u)
        n2 = normal(key, rng_ctr, u)
        if best == NEW_ANCHOR:
            if n_anchors < capacity:
                # Algorithm 3 lines 1-3: a new anchor at the particle's position with covariance R
                map_mu[u, m, n_anchors, 0] = sx
                map_mu[u, m, n_anchors, 1] = sy
                map_cov[u, m, n_anchors, 0] = r
                map_cov[u, m, n_anchors, 1] = 0.0
                map_cov[u, m, n_anchors, 2] = r
                map_type[u, m, n_anchors] = det
                map_count[u, m, n_anchors] = 1
                map_known[u, m, n_anchors] = False
                map_crowd_id[u, m, n_anchors] = -1
                map_n[u, m] = n_anchors + 1
                used_slot[i, m] = n_anchors
            else:
                overflow[u] += 1
                used_slot[i, m] = -1
        else:
            # Algorithm 1 with J_s = -I: Sigma_s = (Q^-1 + P^-1)^-1, mu_s = s + Sigma_s Q^-1 (mu_n - s)
            q_xx = map_cov[u, m, best, 0] + r
            q_xy = map_cov[u, m, best, 1]
            q_yy = map_cov[u, m, best, 2] + r
            dq = q_xx * q_yy - q_xy * q_xy
            qi_xx = q_yy / dq
            qi_xy = -q_xy / dq
            qi_yy = q_xx / dq
            dp = p_xx * p_yy - p_xy * p_xy
            a_xx = qi_xx + p_yy / dp
            a_xy = qi_xy - p_xy / dp
            a_yy = qi_yy + p_xx / dp
            da = a_xx * a_yy - a_xy * a_xy
            s_xx = a_yy / da
            s_xy = -a_xy / da
            s_yy = a_xx / da
            ex = map_mu[u, m, best, 0] - sx
            ey = map_mu[u, m, best, 1] - sy
            gx = qi_xx * ex + qi_xy * ey
            gy = qi_xy * ex + qi_yy * ey
            mx = sx + s_xx * gx + s_xy * gy
            my = sy + s_xy * gx + s_yy * gy
            used_slot[i, m] = best
            nsx, nsy = sample2(mx, my, s_xx, s_xy, s_yy, n1, n2)
            x[u, m] = nsx
            y[u, m] = nsy
            if not map_known[u, m, best]:
                # Algorithm 3 lines 5-7: K = Sigma_n Q^-1; mu += K (s - mu); Sigma = (I - K) Sigma_n
                c_xx = map_cov[u, m, best, 0]
                c_xy = map_cov[u, m, best, 1]
                c_yy = map_cov[u, m, best, 2]
                k11 = c_xx * qi_xx + c_xy * qi_xy
                k12 = c_xx * qi_xy + c_xy * qi_yy
                k21 = c_xy * qi_xx + c_yy * qi_xy
                k22 = c_xy * qi_xy + c_yy * qi_yy
                dx = nsx - map_mu[u, m, best, 0]
                dy = nsy - map_mu[u, m, best, 1]
                map_mu[u, m, best, 0] += k11 * dx + k12 * dy
                map_mu[u, m, best, 1] += k21 * dx + k22 * dy
                n_xx = (1.0 - k11) * c_xx - k12 * c_xy
                n_xy = (1.0 - k11) * c_xy - k12 * c_yy
                n_yy = -k21 * c_xy + (1.0 - k22) * c_yy
                map_cov[u, m, best, 0] = n_xx
                map_cov[u, m, best, 1] = n_xy
                map_cov[u, m, best, 2] = n_yy
            map_count[u, m, best] += 1
        logw[u, m] += best_log  # Eq. 17: w_t = w_{t-1} p_n_hat
    finish_observation(logw, ctrl_cov, degenerate, u)


# The prange wrapper restates its per-user body's parameters: the body stays a plain @njit function because
# numba's parfor pass slowed loops inlined in a prange 2.5x (``motion_update``).
@njit(cache=True, nogil=True, parallel=True)
def building_anchor_update(
    arrays: FilterArrays,
    users: np.ndarray,
    detected_type: np.ndarray,
    anchors: tuple[np.ndarray, float, float],
    used_slot: np.ndarray,
) -> None:
    """Each i: user ``users[i]`` detected an anchor of type ``detected_type[i]``. Users distinct per call.
    ``anchors`` is (type posterior p(f | f_hat), detection sigma, a new anchor's likelihood p0).
    ``used_slot[i, m]`` receives the map slot particle m associated with or created (-1: map full)."""
    for i in prange(users.shape[0]):
        _update_user(i, arrays, users, detected_type, anchors, used_slot)


@njit(cache=True, nogil=True, parallel=True)
def merge_crowd_anchors(
    arrays: FilterArrays,
    users: np.ndarray,
    crowd: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Append to every particle map of ``users`` each crowd anchor whose id it does not hold; ``crowd`` is
    the crowd map's (mean, cov, type, known, id)."""
    map_mu, map_cov, map_type, map_count, map_known, map_crowd_id, map_n = particle_maps(arrays)
    overflow = arrays[N_MAP_OVERFLOW]
    crowd_mean, crowd_cov, crowd_type, crowd_known, crowd_id = crowd
    n_particles = map_mu.shape[1]
    capacity = map_mu.shape[2]
    for i in prange(users.shape[0]):
        u = users[i]
        for m in range(n_particles):
            for c in range(crowd_id.shape[0]):
                present = False
                for k in range(map_n[u, m]):
                    if map_crowd_id[u, m, k] == crowd_id[c]:
                        present = True
                        break
                if present:
                    continue
                n = map_n[u, m]
                if n >= capacity:
                    overflow[u] += 1
                    continue
                map_mu[u, m, n, 0] = crowd_mean[c, 0]
                map_mu[u, m, n, 1] = crowd_mean[c, 1]
                map_cov[u, m, n, 0] = crowd_cov[c, 0]
                map_cov[u, m, n, 1] = crowd_cov[c, 1]
                map_cov[u, m, n, 2] = crowd_cov[c, 2]
                map_type[u, m, n] = crowd_type[c]
                map_count[u, m, n] = 0
                map_known[u, m, n] = crowd_known[c]
                map_crowd_id[u, m, n] = crowd_id[c]
                map_n[u, m] = n + 1


building_anchor_update_serial = serial_twin(building_anchor_update)
merge_crowd_anchors_serial = serial_twin(merge_crowd_anchors)
