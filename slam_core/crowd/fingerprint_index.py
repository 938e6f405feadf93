"""An inverted index of placed WiFi scans by AP, and the union-fingerprint distance of a query to every
reference that shares an AP with it, compiled (``slam_core.crowd.fingerprints`` owns the arrays).

Layout. Each AP (an interned column) has a slab of postings in one pool: ``start[c]``, ``length[c]``,
``capacity[c]``; a posting is (reference row, the row's serial when it was posted, RSS gain). A full slab
moves to the end of the pool with twice the room, so appending is O(1) amortised. References live in a ring
of rows: when a row is overwritten its serial changes, and its old postings become stale; they are skipped
by queries and dropped when the pool is compacted. The cost of a query is the number of postings of its
APs, not references x APs: a 2,400-AP mall floor needs no dense references x APs matrix.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from slam_core.wifi.similarity import union_rms


@njit(cache=True, nogil=True)
def room_needed(cols: np.ndarray, length: np.ndarray, capacity: np.ndarray) -> int:
    """Pool entries that ``append`` will take from the end of the pool for these columns (slabs that move)."""
    need = 0
    for c in cols:
        if length[c] == capacity[c]:
            need += max(4, 2 * capacity[c])
    return need


# The kernels take the index's arrays one by one (start, length, capacity and the postings), as numba
# compiles plain arrays; they share those parameters and nothing else.
@njit(cache=True, nogil=True)
def append(
    cols: np.ndarray,
    gains: np.ndarray,
    row: int,
    serial: int,
    start: np.ndarray,
    length: np.ndarray,
    capacity: np.ndarray,
    post_row: np.ndarray,
    post_serial: np.ndarray,
    post_gain: np.ndarray,
    pool_end: int,
) -> int:
    """Post one reference under each of its columns; returns the new end of the pool. The caller made sure
    the pool holds ``room_needed`` more entries past ``pool_end``."""
    for j in range(cols.size):
        c = cols[j]
        if length[c] == capacity[c]:  # move the slab to the end with twice the room
            new_capacity = max(4, 2 * capacity[c])
            for k in range(length[c]):
                post_row[pool_end + k] = post_row[start[c] + k]
                post_serial[pool_end + k] = post_serial[start[c] + k]
                post_gain[pool_end + k] = post_gain[start[c] + k]
            start[c] = pool_end
            capacity[c] = new_capacity
            pool_end += new_capacity
        p = start[c] + length[c]
        post_row[p] = row
        post_serial[p] = serial
        post_gain[p] = gains[j]
        length[c] += 1
    return pool_end


@njit(cache=True, nogil=True)
def compact(
    start: np.ndarray,
    length: np.ndarray,
    capacity: np.ndarray,
    post_row: np.ndarray,
    post_serial: np.ndarray,
    post_gain: np.ndarray,
    row_serial: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The pool rewritten without stale postings, each slab with room for half as many again (at least 4; none
    for a column left empty); ``start``, ``length`` and ``capacity`` are updated in place. Returns the new
    pool and its end."""
    n_cols = start.size
    live = np.zeros(n_cols, dtype=np.int64)
    kept = np.empty(post_row.size, dtype=np.int64)  # the live postings, column by column
    n_kept = 0
    for c in range(n_cols):
        for p in range(start[c], start[c] + length[c]):
            if row_serial[post_row[p]] == post_serial[p]:
                kept[n_kept] = p
                n_kept += 1
                live[c] += 1
    room = np.where(live == 0, 0, np.maximum(4, live + live // 2))
    total = int(room.sum())
    new_row = np.empty(total, dtype=np.int64)
    new_serial = np.empty(total, dtype=np.int64)
    new_gain = np.empty(total, dtype=np.float32)
    end = 0
    k = 0
    for c in range(n_cols):
        for n in range(live[c]):
            p = kept[k + n]
            new_row[end + n] = post_row[p]
            new_serial[end + n] = post_serial[p]
            new_gain[end + n] = post_gain[p]
        k += live[c]
        start[c] = end
        length[c] = live[c]
        capacity[c] = room[c]
        end += room[c]
    return new_row, new_serial, new_gain, end


@njit(cache=True, nogil=True)
def union_nearest(
    cols: np.ndarray,
    gains: np.ndarray,
    query_norm: float,
    query_count: int,
    owner: int,
    start: np.ndarray,
    length: np.ndarray,
    post_row: np.ndarray,
    post_serial: np.ndarray,
    post_gain: np.ndarray,
    row_serial: np.ndarray,
    row_owner: np.ndarray,
    row_norm: np.ndarray,
    row_count: np.ndarray,
    dot: np.ndarray,
    shared: np.ndarray,
    k: int,
    row_xy: np.ndarray,
    centre_x: float = 0.0,
    centre_y: float = 0.0,
    radius_m: float = math.inf,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The ``k`` live references of other owners nearest to the query by union-fingerprint distance
    (``slam_core.wifi.similarity.union_rms``, from the gains above the floor), among
    those that share an AP with it and lie within ``radius_m`` of the centre (everywhere by default): their
    rows and distances, nearest first, and how many were candidates.
    ``cols`` and ``gains`` are the query's APs known to the index; ``query_norm`` and ``query_count`` are over
    all of its APs. ``dot`` and ``shared`` are per-row scratch, zero on entry and left zero."""
    # The walk is branch-free: whether a posting is live, and whether it is its row's first, are as good as
    # random, and mispredicted branches would cost the walk more than the arithmetic (bench/fingerprints.py
    # measures it). A stale posting adds nothing, and
    # ``touched`` always takes the row but keeps it only when it counts. A user's own rows are skipped after.
    touched = np.empty(row_serial.size + 1, dtype=np.int64)
    n_touched = 0
    for j in range(cols.size):
        q = float(gains[j])
        c = cols[j]
        for p in range(start[c], start[c] + length[c]):
            r = post_row[p]
            live = row_serial[r] == post_serial[p]
            seen = shared[r]
            touched[n_touched] = r
            n_touched += live and seen == 0
            shared[r] = seen + live
            dot[r] += float(post_gain[p]) * q * live
    best_row = np.full(k, -1, dtype=np.int64)
    best = np.full(k, math.inf)
    candidates = 0
    limit = radius_m * radius_m
    bounded = limit < math.inf  # without a radius no row's position is read: the fixes' queries stay as cheap
    for i in range(n_touched):
        r = touched[i]
        n_shared = shared[r]
        product = dot[r]
        dot[r] = 0.0
        shared[r] = 0
        if row_owner[r] == owner:
            continue
        if bounded and (row_xy[r, 0] - centre_x) ** 2 + (row_xy[r, 1] - centre_y) ** 2 > limit:
            continue
        candidates += 1
        d = union_rms(row_norm[r], query_norm, product, int(row_count[r]), query_count, n_shared)
        if d < best[k - 1]:  # insert into the sorted top k (earlier rows win ties)
            j = k - 1
            while j > 0 and best[j - 1] > d:
                best[j] = best[j - 1]
                best_row[j] = best_row[j - 1]
                j -= 1
            best[j] = d
            best_row[j] = r
    n = min(k, candidates)
    return best_row[:n].copy(), best[:n].copy(), candidates


@njit(cache=True, nogil=True)
def locate_many(
    cols: np.ndarray,
    gains: np.ndarray,
    offsets: np.ndarray,
    query_norm: np.ndarray,
    query_count: np.ndarray,
    owner: np.ndarray,
    start: np.ndarray,
    length: np.ndarray,
    post_row: np.ndarray,
    post_serial: np.ndarray,
    post_gain: np.ndarray,
    row_serial: np.ndarray,
    row_owner: np.ndarray,
    row_norm: np.ndarray,
    row_count: np.ndarray,
    dot: np.ndarray,
    shared: np.ndarray,
    k: int,
    row_xy: np.ndarray,
    max_spread: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted-kNN positions of many queries in one call (query q's entries are
    ``cols[offsets[q]:offsets[q + 1]]``, as ``union_nearest`` takes them): (n, 2) positions and whether each
    was placed (at least ``k`` candidates, neighbours within ``max_spread`` of their position). A call's
    queries cost one dispatch instead of one each (a busy building locates hundreds a call)."""
    n = offsets.size - 1
    xy = np.zeros((n, 2))
    placed = np.zeros(n, dtype=np.bool_)
    for q in range(n):
        lo, hi = offsets[q], offsets[q + 1]
        rows, d, candidates = union_nearest(
            cols[lo:hi], gains[lo:hi], query_norm[q], query_count[q], owner[q], start, length, post_row,
            post_serial, post_gain, row_serial, row_owner, row_norm, row_count, dot, shared, k, row_xy,
            0.0, 0.0, math.inf,
        )  # fmt: skip
        if candidates < k:  # fewer than k references share an AP with the query
            continue
        x, y, spread = knn_position(row_xy, rows, d)
        if spread > max_spread:  # the neighbours disagree: the map does not know this place
            continue
        xy[q, 0] = x
        xy[q, 1] = y
        placed[q] = True
    return xy, placed


@njit(cache=True, nogil=True)
def knn_position(row_xy: np.ndarray, rows: np.ndarray, distance: np.ndarray) -> tuple[float, float, float]:
    """Weighted kNN (weights 1/d, d floored at 1e-3 dB) over the neighbours' positions: the position and the
    weighted RMS distance of the neighbours about it."""
    total = 0.0
    x = 0.0
    y = 0.0
    for i in range(rows.size):
        w = 1.0 / max(distance[i], 1e-3)
        total += w
        x += w * row_xy[rows[i], 0]
        y += w * row_xy[rows[i], 1]
    x /= total
    y /= total
    spread = 0.0
    for i in range(rows.size):
        w = 1.0 / max(distance[i], 1e-3)
        spread += w * ((row_xy[rows[i], 0] - x) ** 2 + (row_xy[rows[i], 1] - y) ** 2)
    return x, y, math.sqrt(spread / total)
