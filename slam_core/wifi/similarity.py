"""How alike two WiFi scans are: each measure written once, as a compiled kernel that every caller uses (the
encounter search, the crowd's fingerprint index, the pair features, SignalSLAM's kernels). Their plain NumPy
references, the oracles, live in the tests.

- **DynamicSLAM Eq. 3**: Sim = ||U1 - U2|| / n over the n APs common to both scans' strongest N (Table 2:
  N = 5), U the RSS vectors of those APs. A scan is given as its strongest N AP ids (-1 padded at the end) and
  their RSS.
- **The union-fingerprint distance** (ours, beyond the paper): the RMS difference in dB over the *union* of
  both scans' APs, an AP missing from one scan counting as the floor. Eq. 3 looks at five APs and ignores
  every AP only one phone hears; on a mall's 100+ visible APs an AP heard strongly by one phone and not at
  all by the other is strong evidence that they are apart, and the union keeps it. With gains over the floor
  g = max(rss, floor) - floor, the sum of squares over the union is |g_a|^2 + |g_b|^2 - 2 g_a . g_b (a
  missing AP has gain 0), so every caller gathers the two norms, the dot product and the shared count its
  own way (a walk over an inverted index, matrix products) and the distance is taken here.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True)
def eq3(ap_a: np.ndarray, rss_a: np.ndarray, ap_b: np.ndarray, rss_b: np.ndarray) -> tuple[float, int]:
    """DynamicSLAM Eq. 3 between two scans' strongest N (AP ids, -1 padded; their RSS): (Sim in dB, n
    common); (inf, 0) with no AP in common. Summed in scan b's order."""
    total = 0.0
    n = 0
    for k in range(ap_b.size):
        ap = ap_b[k]
        if ap < 0:
            break
        for i in range(ap_a.size - 1, -1, -1):  # the last entry of a repeated AP, as a table of a's APs keeps
            if ap_a[i] == ap:
                d = rss_a[i] - rss_b[k]
                total += d * d
                n += 1
                break
    if n == 0:
        return math.inf, 0
    return math.sqrt(total) / n, n


@njit(cache=True, nogil=True)
def union_rms(squares_a: float, squares_b: float, dot: float, n_a: int, n_b: int, shared: int) -> float:
    """The union-fingerprint distance from gains over the floor: ``squares`` = |g|^2 of each scan, ``dot`` =
    g_a . g_b over the ``shared`` APs, ``n`` = each scan's APs; inf for two empty scans."""
    union = n_a + n_b - shared
    if union <= 0:
        return math.inf
    return math.sqrt(max(squares_a + squares_b - 2.0 * dot, 0.0) / union)


@njit(cache=True, nogil=True, parallel=True)
def eq3_matrix(top_ap: np.ndarray, top_rss: np.ndarray, min_common: int) -> np.ndarray:
    """Eq. 3 between every pair of scans (rows of ``top_ap``/``top_rss``: each scan's strongest N); +inf
    where fewer than ``min_common`` (at least one) APs are common."""
    s = top_ap.shape[0]
    out = np.empty((s, s))
    for i in prange(s):
        for j in range(s):
            sim, n = eq3(top_ap[i], top_rss[i], top_ap[j], top_rss[j])
            out[i, j] = sim if n >= max(min_common, 1) else math.inf
    return out


@njit(cache=True, nogil=True, parallel=True)
def union_rms_matrix(
    squares_a: np.ndarray,
    squares_b: np.ndarray,
    dot: np.ndarray,
    n_a: np.ndarray,
    n_b: np.ndarray,
    shared: np.ndarray,
) -> np.ndarray:
    """``union_rms`` of every pair (i, j): the scans' squares and counts per row (a) and column (b), their
    dot products and shared counts as (A, B) matrices."""
    out = np.empty(dot.shape)
    for i in prange(dot.shape[0]):
        for j in range(dot.shape[1]):
            out[i, j] = union_rms(
                squares_a[i], squares_b[j], dot[i, j], int(n_a[i]), int(n_b[j]), round(shared[i, j])
            )
    return out
