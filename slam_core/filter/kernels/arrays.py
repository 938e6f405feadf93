"""The filter's arrays as the kernels take them: one tuple (``FilterState.arrays``), read by these indices.

A kernel takes the bundle and picks what it uses, ``x = arrays[X]``: the indices are module constants, which
numba folds, so each pick is typed and costs nothing. One bundle instead of a kernel's twenty arrays keeps
the batch kernels' signatures short and their per-user bodies' alike, and dispatches no slower than as many
arrays (a parallel region faster). Each array passed costs a call's dispatch, so a small kernel that reads
a few of them (the human-anchor update) takes just those.
"""

from __future__ import annotations

import numpy as np
from numba import njit

FIELDS = (
    "x",
    "y",
    "heading",
    "bias",
    "scale",
    "walk",
    "logw",
    "map_mu",
    "map_cov",
    "map_type",
    "map_count",
    "map_known",
    "map_crowd_id",
    "map_n",
    "ctrl_cov",
    "last_obs_heading",
    "rng_key",
    "rng_ctr",
    "n_resamples",
    "n_map_overflow",
    "n_degenerate",
)
"""``FilterState``'s fields in the bundle, in order (``slam_core.filter.state`` documents each)."""

(
    X,
    Y,
    HEADING,
    BIAS,
    SCALE,
    WALK,
    LOGW,
    MAP_MU,
    MAP_COV,
    MAP_TYPE,
    MAP_COUNT,
    MAP_KNOWN,
    MAP_CROWD_ID,
    MAP_N,
    CTRL_COV,
    LAST_OBS_HEADING,
    RNG_KEY,
    RNG_CTR,
    N_RESAMPLES,
    N_MAP_OVERFLOW,
    N_DEGENERATE,
) = range(len(FIELDS))

FilterArrays = tuple[np.ndarray, ...]


@njit(cache=True, nogil=True, inline="always")
def particle_maps(
    arrays: FilterArrays,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every particle's anchor map: (mu, cov, type, count, known, crowd id, anchors in use)."""
    return (
        arrays[MAP_MU],
        arrays[MAP_COV],
        arrays[MAP_TYPE],
        arrays[MAP_COUNT],
        arrays[MAP_KNOWN],
        arrays[MAP_CROWD_ID],
        arrays[MAP_N],
    )
