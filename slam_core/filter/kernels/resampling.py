"""Resampling schemes (index draws) and the batched resample-and-gather kernel.

Schemes by name, as in ``particles``: systematic (default), stratified, residual, multinomial. Each takes
normalised weights and the user's RNG stream and writes ancestor indices.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from slam_core.filter.kernels.arrays import (
    BIAS,
    HEADING,
    LOGW,
    N_RESAMPLES,
    RNG_CTR,
    RNG_KEY,
    SCALE,
    WALK,
    FilterArrays,
    X,
    Y,
    particle_maps,
)
from slam_core.filter.kernels.rng import normal_at, uniform
from slam_core.filter.kernels.serial import serial_twin
from slam_core.filter.kernels.weights import effective_sample_size

SYSTEMATIC = 0
STRATIFIED = 1
RESIDUAL = 2
MULTINOMIAL = 3
SCHEME_CODES = {
    "systematic": SYSTEMATIC,
    "stratified": STRATIFIED,
    "residual": RESIDUAL,
    "multinomial": MULTINOMIAL,
}


@njit(cache=True, nogil=True)
def _inverse_cdf(sorted_uniforms: np.ndarray, w: np.ndarray, out: np.ndarray, start: int) -> None:
    """Ancestors for increasing uniforms in [0, 1): out[start + k] = min{j : cumsum(w)[j] > u_k}."""
    j = 0
    cumulative = w[0]
    last = w.shape[0] - 1
    for k in range(sorted_uniforms.shape[0]):
        while sorted_uniforms[k] >= cumulative and j < last:
            j += 1
            cumulative += w[j]
        out[start + k] = j


@njit(cache=True, nogil=True)
def draw_ancestors(
    w: np.ndarray, scheme: int, key: np.uint64, counters: np.ndarray, user: int, out: np.ndarray
) -> None:
    """Write the ancestors of the particles weighted ``w`` into ``out``."""
    n = w.shape[0]
    if scheme == SYSTEMATIC:
        u0 = uniform(key, counters, user)
        us = (np.arange(n) + u0) / n
        _inverse_cdf(us, w, out, 0)
    elif scheme == STRATIFIED:
        us = np.empty(n)
        for k in range(n):
            us[k] = (k + uniform(key, counters, user)) / n
        _inverse_cdf(us, w, out, 0)
    elif scheme == MULTINOMIAL:
        us = np.empty(n)
        for k in range(n):
            us[k] = uniform(key, counters, user)
        us.sort()
        _inverse_cdf(us, w, out, 0)
    else:  # RESIDUAL: floor(n w) copies deterministically, the rest multinomially on the residuals
        filled = 0
        residual = np.empty(n)
        for j in range(n):
            copies = int(n * w[j])  # n w >= 0, so truncation is the floor
            for _ in range(copies):
                out[filled] = j
                filled += 1
            residual[j] = n * w[j] - copies
        rest = n - filled
        if rest > 0:
            total = residual.sum()
            residual /= total
            us = np.empty(rest)
            for k in range(rest):
                us[k] = uniform(key, counters, user)
            us.sort()
            _inverse_cdf(us, residual, out, filled)


@njit(cache=True, nogil=True)
def _gather_maps(u: int, idx: np.ndarray, arrays: FilterArrays) -> None:
    """Particle m's map becomes a copy of its ancestor idx[m]'s. Only the slots up to the fullest ancestor's
    ``map_n`` are copied (slots past a particle's ``map_n`` are never read): copying whole map capacities
    dominated the resampling of young maps."""
    map_mu, map_cov, map_type, map_count, map_known, map_crowd_id, map_n = particle_maps(arrays)
    k = 0
    for m in range(idx.shape[0]):
        k = max(k, map_n[u, idx[m]])
    if k == 0:  # no ancestor holds an anchor: nothing to copy
        map_n[u] = 0
        return
    map_mu[u, :, :k] = map_mu[u][idx, :k]
    map_cov[u, :, :k] = map_cov[u][idx, :k]
    map_type[u, :, :k] = map_type[u][idx, :k]
    map_count[u, :, :k] = map_count[u][idx, :k]
    map_known[u, :, :k] = map_known[u][idx, :k]
    map_crowd_id[u, :, :k] = map_crowd_id[u][idx, :k]
    map_n[u] = map_n[u][idx]


@njit(cache=True, nogil=True)
def _resample_user(
    u: int, arrays: FilterArrays, threshold: float, scheme: int, roughening: tuple[float, float]
) -> None:
    x, y, heading = arrays[X], arrays[Y], arrays[HEADING]
    bias, scale, walk, logw = arrays[BIAS], arrays[SCALE], arrays[WALK], arrays[LOGW]
    rng_key, rng_ctr, n_resamples = arrays[RNG_KEY], arrays[RNG_CTR], arrays[N_RESAMPLES]
    roughening_bias, roughening_scale = roughening
    n_particles = logw.shape[1]
    if threshold < 1.0 and effective_sample_size(logw, u) >= threshold * n_particles:
        return
    # one scratch row for the weights, then each gathered field; the ancestors in another (allocating per
    # field cost more than the copies)
    scratch = np.empty(n_particles)
    total = 0.0
    for m in range(n_particles):
        scratch[m] = math.exp(logw[u, m])
        total += scratch[m]
    for m in range(n_particles):
        scratch[m] /= total
    idx = np.empty(n_particles, dtype=np.int64)
    draw_ancestors(scratch, scheme, rng_key[u], rng_ctr, u, idx)
    for field in (x, y, heading, bias, scale, walk):
        for m in range(n_particles):
            scratch[m] = field[u, idx[m]]
        for m in range(n_particles):
            field[u, m] = scratch[m]
    _gather_maps(u, idx, arrays)
    key = rng_key[u]
    uniform_logw = -math.log(n_particles)
    for m in range(n_particles):
        logw[u, m] = uniform_logw
    if roughening_bias > 0.0 or roughening_scale > 0.0:
        counter = rng_ctr[u]  # kept local: a counter written back at every draw serialised the loop
        one = np.uint64(1)
        for m in range(n_particles):
            bias[u, m] += roughening_bias * normal_at(key, counter)
            scale[u, m] = max(0.2, scale[u, m] + roughening_scale * normal_at(key, counter + one))
            counter += np.uint64(2)
        rng_ctr[u] = counter
    n_resamples[u] += 1


@njit(cache=True, nogil=True, parallel=True)
def resample_users(
    arrays: FilterArrays, users: np.ndarray, threshold: float, scheme: int, roughening: tuple[float, float]
) -> None:
    """Resample every listed user whose ESS < threshold * M (threshold 1.0: always, as Algorithm 2 does);
    ``roughening`` is the (bias, scale) jitter each particle then gets."""
    for i in prange(users.shape[0]):
        _resample_user(users[i], arrays, threshold, scheme, roughening)


resample_users_serial = serial_twin(resample_users)
