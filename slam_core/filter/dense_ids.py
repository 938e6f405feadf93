"""Sorted unique values of small non-negative integers (filter slots, interned user ids) by a table instead of
a sort.

A busy tracker call holds thousands of encounter detections, whose user ids and slots ``np.unique`` would
sort several times a call. Ids and slots are bounded by the users the building has seen, so a boolean table as
long as the largest value finds the same answer in one pass. Short arrays (where the table's set-up costs
more than the sort), and values that are negative or spread far wider than the array is long, go to
``np.unique``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_MIN_SIZE = 64
_TABLE_SLACK = 65_536
"""A table may be this much longer than four times the array (a few hundred kB at most) before a sort wins."""


def unique_ints(values: np.ndarray) -> np.ndarray:
    """``np.unique(values)`` for a 1-D integer array."""
    size = _table_size(values)
    if size is None:
        return np.unique(values)
    return _present(values, size).astype(values.dtype, copy=False)


def unique_ints_inverse(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(values, return_inverse=True)`` for a 1-D integer array."""
    size = _table_size(values)
    if size is None:
        uniques, inverse = np.unique(values, return_inverse=True)
        return uniques, inverse.reshape(-1)
    uniques = _present(values, size)
    position = np.empty(size, dtype=np.intp)
    position[uniques] = np.arange(uniques.size)
    return uniques.astype(values.dtype, copy=False), position[values]


def _table_size(values: np.ndarray) -> int | None:
    """The table's length (the largest value + 1), or None when ``np.unique`` is the better way."""
    if values.ndim != 1 or values.dtype.kind not in "iu":
        raise ValueError(f"expected a 1-D integer array, got {values.dtype} of shape {values.shape}")
    if values.size < _MIN_SIZE or int(values.min()) < 0:
        return None
    size = int(values.max()) + 1
    return size if size <= 4 * values.size + _TABLE_SLACK else None


def _present(values: np.ndarray, size: int) -> np.ndarray:
    present = np.zeros(size, dtype=bool)
    present[values] = True
    return np.flatnonzero(present)


FINE, UNKNOWN, REPEATED = 0, 1, 2


@njit(cache=True, nogil=True)
def slots_problem(slots: np.ndarray, active: np.ndarray, seen: np.ndarray, stamp: int, repeats: bool) -> int:
    """Whether every slot is an active one (else ``UNKNOWN``) and, unless ``repeats``, none appears twice
    (else ``REPEATED``), by marking ``seen`` (as long as ``active``) with this call's ``stamp``: one pass,
    where ``np.unique`` sorted the slots on every tracker call (seven a tracker call)."""
    n = active.size
    for u in slots:
        if u < 0 or u >= n or not active[u]:
            return UNKNOWN
    if not repeats:
        for u in slots:
            if seen[u] == stamp:
                return REPEATED
            seen[u] = stamp
    return FINE
