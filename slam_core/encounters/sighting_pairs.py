"""Bluetooth sightings averaged per pair of phones (DynamicSLAM Section 4.1.2's RSS cut-off, both directions
over one sighting period), for a whole tracker call's sightings in one compiled pass.

Each pair that was heard recently has an entry in an open-addressing table of pair keys; its sightings
within the smoothing window are a first-in first-out chain in a pool of (time, RSS) cells; and the entries
are linked from the least to the most recently heard, so that time moving on forgets the pairs silent for
``retention_ms`` by looking only at the front of that list. Everything is a handful of arrays: the garbage
collector does not walk them and a snapshot pickles each as one block, where a dict of per-pair histories
cost a dict operation and a bytes object per sighting, in Python.

The outcome is the per-sighting definition exactly: a sighting's pair average is the sum of its window's
RSS in arrival order over their number, the window cut at the front (by arrival) while its oldest is
``smoothing_ms`` behind the new sighting, and a pair is forgotten when the newest time seen moves more than
``retention_ms`` past its last sighting while it is the least recently heard.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_EMPTY = np.int64(-1)
"""A table entry never used (pair keys are >= 0)."""
_GONE = np.int64(-2)
"""A table entry whose pair was forgotten: lookups probe past it, insertions may reuse it."""
_NONE = -1

# meta: the list's ends, the live and forgotten entries, the pool's free chain and its length, the newest time
_HEAD, _TAIL, _COUNT, _GONE_COUNT, _FREE, _FREE_COUNT, _NEWEST = range(7)


class SightingPairs:
    """The recent sightings of every pair of one building's phones (users as the detector's interned ids,
    below 2^31)."""

    def __init__(self, capacity: int = 64, pool: int = 256) -> None:
        self.keys = np.full(capacity, _EMPTY, dtype=np.int64)
        self.first = np.full(capacity, _NONE, dtype=np.int64)  # the oldest cell of the pair's window
        self.last = np.full(capacity, _NONE, dtype=np.int64)  # its newest
        self.older = np.full(capacity, _NONE, dtype=np.int64)  # the entry heard just before (the list)
        self.newer = np.full(capacity, _NONE, dtype=np.int64)
        self.cell_t = np.zeros(pool)  # ms, exact in a double
        self.cell_rss = np.zeros(pool)
        self.cell_next = np.arange(1, pool + 1, dtype=np.int64)  # the window's next cell, or the free chain
        self.cell_next[-1] = _NONE
        self.meta = np.array([_NONE, _NONE, 0, 0, 0, pool, 0], dtype=np.int64)

    def __len__(self) -> int:
        return int(self.meta[_COUNT])

    def add(
        self,
        a: np.ndarray,
        b: np.ndarray,
        t_ms: np.ndarray,
        rss_dbm: np.ndarray,
        smoothing_ms: int,
        retention_ms: int,
        cutoff_dbm: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sightings of ``b`` by ``a`` (a != b), in arrival order: which pass the cut-off on their pair's
        average (indices), and those averages."""
        n = int(t_ms.size)
        self._make_room(n)
        passed = np.empty(n, dtype=np.int64)
        smoothed = np.empty(n)
        m = _add(
            np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64), np.asarray(t_ms, dtype=np.int64),
            np.asarray(rss_dbm, dtype=np.float64), smoothing_ms, retention_ms, cutoff_dbm, self.keys,
            self.first, self.last, self.older, self.newer, self.cell_t, self.cell_rss, self.cell_next,
            self.meta, passed, smoothed,
        )  # fmt: skip
        return passed[:m], smoothed[:m]

    def pairs(self) -> list[tuple[int, int]]:
        """The pairs kept, from the least recently heard (each as its two ids, the smaller first)."""
        out = []
        entry = int(self.meta[_HEAD])
        while entry != _NONE:
            key = int(self.keys[entry])
            out.append((key >> 32, key & 0xFFFF_FFFF))
            entry = int(self.newer[entry])
        return out

    def _make_room(self, more: int) -> None:
        """Room for ``more`` new pairs (the table at most half full, forgotten entries counted) and ``more``
        new cells."""
        meta = self.meta
        if 2 * (meta[_COUNT] + meta[_GONE_COUNT] + more) > self.keys.size:
            capacity = 64
            while 2 * (meta[_COUNT] + more) > capacity:
                capacity *= 2
            self._rebuild(capacity)
        if meta[_FREE_COUNT] < more:
            old = self.cell_t.size
            size = max(2 * old, old + more)
            self.cell_t = np.concatenate([self.cell_t, np.zeros(size - old)])
            self.cell_rss = np.concatenate([self.cell_rss, np.zeros(size - old)])
            chain = np.arange(old + 1, size + 1, dtype=np.int64)
            chain[-1] = meta[_FREE]  # the new cells, then the free ones there were
            self.cell_next = np.concatenate([self.cell_next, chain])
            meta[_FREE] = old
            meta[_FREE_COUNT] += size - old

    def _rebuild(self, capacity: int) -> None:
        keys = np.full(capacity, _EMPTY, dtype=np.int64)
        first, last, older, newer = (np.full(capacity, _NONE, dtype=np.int64) for _ in range(4))
        _rebuild(self.keys, self.first, self.last, self.newer, self.meta, keys, first, last, older, newer)
        self.keys, self.first, self.last, self.older, self.newer = keys, first, last, older, newer


@njit(cache=True, nogil=True)
def home_slot(key: np.int64, mask: int) -> int:
    """Where a pair key's probe starts in an open-addressing table of ``mask + 1`` entries (a power of two):
    a Fibonacci-style scramble of the key. The encounter tables' one hash (these pairs, the selector's
    cooldowns and latest readings)."""
    return int((key * np.int64(-7046029254386353131)) >> np.int64(17)) & mask


@njit(cache=True, nogil=True)
def _find(keys: np.ndarray, key: np.int64) -> tuple[int, int]:
    """Where ``key`` is (or -1), and where it would be inserted (the first forgotten entry on its probe,
    else the free one that ends it)."""
    mask = keys.size - 1  # a power of two
    i = home_slot(key, mask)
    spare = -1
    while keys[i] != _EMPTY:
        if keys[i] == key:
            return i, i
        if keys[i] == _GONE and spare < 0:
            spare = i
        i = (i + 1) & mask
    return -1, (spare if spare >= 0 else i)


@njit(cache=True, nogil=True)
def _unlink(entry: int, older: np.ndarray, newer: np.ndarray, meta: np.ndarray) -> None:
    o, n = older[entry], newer[entry]
    if o == _NONE:
        meta[_HEAD] = n
    else:
        newer[o] = n
    if n == _NONE:
        meta[_TAIL] = o
    else:
        older[n] = o


@njit(cache=True, nogil=True)
def _append(entry: int, older: np.ndarray, newer: np.ndarray, meta: np.ndarray) -> None:
    tail = meta[_TAIL]
    older[entry], newer[entry] = tail, _NONE
    if tail == _NONE:
        meta[_HEAD] = entry
    else:
        newer[tail] = entry
    meta[_TAIL] = entry


@njit(cache=True, nogil=True)
def _release(first: int, cell_next: np.ndarray, meta: np.ndarray) -> None:
    """Return a chain of cells to the free chain."""
    cell = first
    while cell != _NONE:
        following = cell_next[cell]
        cell_next[cell] = meta[_FREE]
        meta[_FREE] = cell
        meta[_FREE_COUNT] += 1
        cell = following


@njit(cache=True, nogil=True)
def _add(
    a: np.ndarray,
    b: np.ndarray,
    t_ms: np.ndarray,
    rss: np.ndarray,
    smoothing_ms: int,
    retention_ms: int,
    cutoff: float,
    keys: np.ndarray,
    first: np.ndarray,
    last: np.ndarray,
    older: np.ndarray,
    newer: np.ndarray,
    cell_t: np.ndarray,
    cell_rss: np.ndarray,
    cell_next: np.ndarray,
    meta: np.ndarray,
    passed: np.ndarray,
    smoothed: np.ndarray,
) -> int:
    m = 0
    for s in range(t_ms.size):
        t = t_ms[s]
        if t > meta[_NEWEST]:  # time moves on: forget the least recently heard pairs silent since the horizon
            meta[_NEWEST] = t
            horizon = t - retention_ms
            while meta[_HEAD] != _NONE:
                entry = meta[_HEAD]
                if cell_t[last[entry]] >= horizon:
                    break
                _unlink(entry, older, newer, meta)
                _release(first[entry], cell_next, meta)
                keys[entry] = _GONE
                meta[_COUNT] -= 1
                meta[_GONE_COUNT] += 1
        lo, hi = min(a[s], b[s]), max(a[s], b[s])
        key = (np.int64(lo) << np.int64(32)) | np.int64(hi)
        at, spare = _find(keys, key)
        cell = meta[_FREE]
        meta[_FREE] = cell_next[cell]
        meta[_FREE_COUNT] -= 1
        cell_t[cell], cell_rss[cell], cell_next[cell] = t, rss[s], _NONE
        if at < 0:
            at = spare
            if keys[at] == _GONE:
                meta[_GONE_COUNT] -= 1
            keys[at] = key
            first[at] = cell
            meta[_COUNT] += 1
        else:
            cell_next[last[at]] = cell
            _unlink(at, older, newer, meta)
        last[at] = cell
        _append(at, older, newer, meta)
        while t - cell_t[first[at]] >= smoothing_ms:  # the window, cut at its front (never the new one)
            gone = first[at]
            first[at] = cell_next[gone]
            cell_next[gone] = meta[_FREE]
            meta[_FREE] = gone
            meta[_FREE_COUNT] += 1
        total = 0.0
        count = 0
        cell = first[at]
        while cell != _NONE:  # summed in arrival order, as the definition reads
            total += cell_rss[cell]
            count += 1
            cell = cell_next[cell]
        average = total / count
        if average >= cutoff:
            passed[m] = s
            smoothed[m] = average
            m += 1
    return m


@njit(cache=True, nogil=True)
def _rebuild(
    keys: np.ndarray,
    first: np.ndarray,
    last: np.ndarray,
    newer: np.ndarray,
    meta: np.ndarray,
    new_keys: np.ndarray,
    new_first: np.ndarray,
    new_last: np.ndarray,
    new_older: np.ndarray,
    new_newer: np.ndarray,
) -> None:
    """The live entries into a new table, walked in their list's order so that it is kept."""
    entry = meta[_HEAD]
    meta[_HEAD] = _NONE
    meta[_TAIL] = _NONE
    while entry != _NONE:
        _, at = _find(new_keys, keys[entry])
        new_keys[at] = keys[entry]
        new_first[at], new_last[at] = first[entry], last[entry]
        _append(at, new_older, new_newer, meta)
        entry = newer[entry]
    meta[_GONE_COUNT] = 0
