"""Log-domain weights: normalisation and effective sample size."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def normalise_log_weights(logw: np.ndarray, u: int) -> bool:
    """Normalise row ``u`` so that sum(exp(logw)) = 1. Returns False, leaving the row untouched, when every
    weight is zero or not finite (the caller recovers explicitly and counts it)."""
    return normalise_log_weights_ess(logw, u) > 0.0


@njit(cache=True, nogil=True)
def normalise_log_weights_ess(logw: np.ndarray, u: int) -> float:
    """``normalise_log_weights``, returning the row's effective sample size from the same exponentials
    (equal to ``effective_sample_size`` afterwards up to rounding), or 0.0 when the row could not be
    normalised."""
    n = logw.shape[1]
    top = -np.inf
    for m in range(n):
        if logw[u, m] > top:
            top = logw[u, m]
    if not math.isfinite(top):
        return 0.0
    total = 0.0
    squares = 0.0
    for m in range(n):
        e = math.exp(logw[u, m] - top)
        total += e
        squares += e * e
    log_total = top + math.log(total)
    for m in range(n):
        logw[u, m] -= log_total
    return total * total / squares


@njit(cache=True, nogil=True)
def finish_observation(logw: np.ndarray, ctrl_cov: np.ndarray, degenerate: np.ndarray, u: int) -> None:
    """End of an observation update of user ``u``: normalise its weights, or, when every weight vanished,
    restart them uniform and count it in ``degenerate`` (explicit recovery, never silent); the control
    covariance since the last correction (P_t) starts again from zero."""
    if not normalise_log_weights(logw, u):
        degenerate[u] += 1
        n_particles = logw.shape[1]
        for m in range(n_particles):
            logw[u, m] = -math.log(n_particles)
    ctrl_cov[u, 0] = 0.0
    ctrl_cov[u, 1] = 0.0
    ctrl_cov[u, 2] = 0.0


@njit(cache=True, nogil=True)
def effective_sample_size(logw: np.ndarray, u: int) -> float:
    """1 / sum(w^2) of the normalised row."""
    s = 0.0
    for m in range(logw.shape[1]):
        w = math.exp(logw[u, m])
        s += w * w
    return 1.0 / s if s > 0.0 else 0.0
