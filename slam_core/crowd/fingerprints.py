"""A WiFi fingerprint map learned by the crowd while it is tracked, and WiFi localisation on it.

Beyond DynamicSLAM (SignalSLAM's fingerprint localisation, Section IV, used live): every fresh WiFi scan of a
tracked user whose estimate is confident joins the map at that estimate; a later scan of another user is
localised by weighted kNN (weights 1/d) over the union-fingerprint distance (``slam_core.wifi.pairs``: RMS dB
over the union of both scans' APs, a missing AP at ``floor_dbm``), and the result becomes a robust position
observation of that user (``DynamicSlam.observe_position_robust``). A user's own scans are never its
references: they would only confirm its own estimate.

Memory is bounded (``max_references``, oldest dropped first) and proportional to the APs the references
heard: the scans are posted in an inverted index by AP (``slam_core.crowd.fingerprint_index``), so a query
costs the postings of its own APs, not references x APs (a dense matrix of a mall floor's thousands of APs by
its references would take hundreds of megabytes).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from slam_core.crowd import fingerprint_index as index
from slam_core.filter.kernels.linalg2 import largest_eigenvalue2

STALE_BOUND = 1.25
"""The index is compacted once its slabs hold more than this many postings per live one. A query walks
every posting of its APs and skips the stale ones, so stale postings cost every query; a compaction costs
what a few queries save (``bench/fingerprints.py``; docs/experiments.md)."""


@dataclass(frozen=True)
class Scan:
    """One WiFi scan of a tracked user: its fresh APs and the user's dead-reckoned displacement since."""

    bssids: list[str]
    rss: np.ndarray
    shift: np.ndarray  # (2,) displacement from the scan to now
    t_ms: int


@dataclass(frozen=True)
class Place:
    """A scan to join the map, at the position its user was estimated to hold then."""

    owner: int
    xy: np.ndarray
    bssids: list[str]
    rss: np.ndarray
    t_ms: int


@dataclass(frozen=True)
class FingerprintParams:
    enabled: bool = False
    k: int = 7
    """Neighbours of the weighted kNN (the fingerprint localisation's k)."""
    sigma_m: float = 15.0
    """The observation's sigma. On msindoor site1 F1 (warm replay) the fixes were off by 6.7 / 11 / 18 m
    (p50 / p75 / p90; a map at surveyed positions reaches 4.6 m p50): a core sigma of ~6 m, widened for
    consecutive scans of one walk, which err alike (the map's error is a place's, not a scan's). Measured:
    sigma 10 m 2.55 / 5.21, 15 m 2.54 / 5.13 (p50 / p90 of the replay; 2.62 / 5.31 without fixes)."""
    outlier_probability: float = 0.3
    """Share of fixes that are wrong (msindoor: the kNN's p90 is about twice its p50, with a long tail)."""
    outlier_radius_m: float = 50.0
    """A wrong fix lands anywhere within this radius: the outlier term's density is 1 / (pi r^2)."""
    max_reference_std_m: float = 3.0
    """A scan joins the map only when its user's estimate is this certain (the larger axis' sigma)."""
    max_spread_m: float = 12.0
    """A scan whose k neighbours lie further apart than this (weighted RMS about their mean) is not
    localised: on msindoor site1 F1 such fixes were off by 11 m p50 (the others by 4.9-7.1 m)."""
    min_references: int = 50
    """No fix before the map holds this many scans of other users."""
    max_references: int = 20_000
    """The whole map's bound (the oldest reference leaves first)."""
    cell_m: float = 4.0
    per_cell: int = 4
    """At most ``per_cell`` references per ``cell_m`` square (by position; the cell's oldest leaves first).
    The map's size then follows the building's area, not its traffic: without it, 2,000 phones scanning
    every 2 s would turn a 20,000-scan map over in 20 s, so that it held only the places walked in the last
    20 s, and a busy corridor's scans would cost every query that hears its APs. One scan per 4 m^2 is
    finer than WiFi tells places apart (kNN errs by ~5 m); on msindoor site1 F1 16, 8 and 4 per cell gave
    the same replay within the seeds' spread, and a query costs the postings of its APs, ~4x fewer at 4
    than at 16 on a dense floor."""
    cell_refresh_ms: int = 30_000
    """A full cell takes a new scan (in place of its oldest) only once its newest is this old (by the phones'
    clocks; a newest as far in the future counts as old, so that no clock running ahead holds a cell). A
    busy floor would otherwise turn every cell over within seconds (2,000 load-bench phones on 600 cells: a
    scan a cell every ~0.6 s), so that the map held only the last few seconds' walkers, whose errors are
    alike, and the building spent ~6 % of its core storing scans it dropped again. At 30 s a full cell
    holds scans at least that far apart, most from different walks; a quiet floor, whose cells fill slower
    than that, keeps every scan."""
    min_aps: int = 3
    """A scan with fewer fresh APs is neither stored nor localised."""
    floor_dbm: float = -100.0

    def __post_init__(self) -> None:
        if self.k < 1 or self.min_references < self.k or self.max_references < self.min_references:
            raise ValueError("fingerprint map needs 1 <= k <= min_references <= max_references")
        if min(self.sigma_m, self.outlier_radius_m, self.max_reference_std_m, self.max_spread_m) <= 0:
            raise ValueError("fingerprint sigmas and radius must be positive")
        if not 0.0 <= self.outlier_probability < 1.0:
            raise ValueError("outlier_probability must be in [0, 1)")
        if self.min_aps < 1:
            raise ValueError("min_aps must be >= 1")
        if not self.cell_m > 0 or self.per_cell < 1:
            raise ValueError("fingerprint cells need cell_m > 0 and per_cell >= 1")
        if self.cell_refresh_ms < 0:
            raise ValueError("cell_refresh_ms must be >= 0")


SURVEY_OWNER = -2
"""The owner of scans placed by a signal-map build (``CrowdFingerprints.add``): no user's, so every user's
scans are located on them."""


NOBODY = -3
"""The owner of a query from a user not yet started: every stored scan is another user's."""


class CrowdFingerprints:
    """Placed scans in at most ``max_references`` rows, bounded per cell of the floor, posted in an inverted
    index by interned BSSID."""

    def __init__(self, params: FingerprintParams) -> None:
        self.params = params
        self._columns: dict[str, int] = {}
        n = min(64, params.max_references)
        self._xy = np.zeros((n, 2))
        self._owner = np.full(n, -1, dtype=np.int64)
        self._norm = np.zeros(n)  # sum of squared gains per row
        self._count = np.zeros(n, dtype=np.int64)  # APs heard per row
        self._serial = np.full(n, -1, dtype=np.int64)  # which scan a row holds (stale postings differ)
        self._t = np.zeros(n, dtype=np.int64)  # when each row's scan was taken (ms)
        self._dot = np.zeros(n)  # query scratch, kept zero between queries
        self._shared = np.zeros(n, dtype=np.int64)
        self._per_owner: dict[int, int] = {}
        self._cells: dict[tuple[int, int], deque[int]] = {}  # rows of each cell, oldest first
        self._cell_of: list[tuple[int, int]] = []  # the cell of each row
        self._by_age: deque[tuple[int, int]] = deque()  # (row, serial), oldest first; stale pairs skipped
        self._size = 0
        self._serial_next = 0
        # the inverted index: one slab of postings per column in one pool
        self._start = np.zeros(16, dtype=np.int64)
        self._length = np.zeros(16, dtype=np.int64)
        self._capacity = np.zeros(16, dtype=np.int64)
        self._post_row = np.zeros(256, dtype=np.int64)
        self._post_serial = np.zeros(256, dtype=np.int64)
        self._post_gain = np.zeros(256, dtype=np.float32)
        self._pool_end = 0
        self._live_postings = 0
        self._posted = 0  # postings in the slabs, live or stale: what a query over every AP would walk

    def __len__(self) -> int:
        return self._size

    @property
    def postings(self) -> int:
        """Pool entries in use, live or stale (for tests and memory accounting)."""
        return self._pool_end

    @property
    def stale_postings(self) -> int:
        """Postings of evicted references still in the slabs (a query walks them and skips them)."""
        return self._posted - self._live_postings

    def _gains(self, bssids: list[str], rss: np.ndarray) -> tuple[list[str], np.ndarray]:
        """A scan's finite entries and their RSS above the floor (a BSSID listed twice counts once,
        strongest)."""
        floor = self.params.floor_dbm
        rss = np.asarray(rss, dtype=float)
        finite = np.isfinite(rss)
        if not finite.all():
            bssids = [b for b, f in zip(bssids, finite.tolist(), strict=True) if f]
            rss = rss[finite]
        gains = np.maximum(rss, floor) - floor
        if len(set(bssids)) != len(bssids):
            strongest: dict[str, float] = {}
            for b, g in zip(bssids, gains.tolist(), strict=True):
                strongest[b] = max(g, strongest.get(b, 0.0))
            bssids, gains = list(strongest), np.fromiter(strongest.values(), float, len(strongest))
        return bssids, gains.astype(np.float32)

    def add(self, owner: int, xy: np.ndarray, bssids: list[str], rss: np.ndarray, t_ms: int) -> bool:
        """Store one scan (fresh entries only) taken at ``t_ms`` at ``xy``; False when it has too few APs, or
        when its cell is full and its newest scan was taken less than ``cell_refresh_ms`` before or after."""
        p = self.params
        if len(bssids) < p.min_aps:
            return False
        cell = (math.floor(float(xy[0]) / p.cell_m), math.floor(float(xy[1]) / p.cell_m))
        rows = self._cells.get(cell)
        # either way round: a phone whose clock runs far ahead must not hold a cell for everyone else
        if rows is not None and len(rows) >= p.per_cell:
            if abs(t_ms - self._t[rows[-1]]) < p.cell_refresh_ms:
                return False
            if owner != SURVEY_OWNER and all(self._owner[r] == SURVEY_OWNER for r in rows):
                return False  # a build placed these better than any estimate: they keep their cell
        heard, gains = self._gains(bssids, rss)
        if len(heard) < p.min_aps:
            return False
        cols = np.fromiter(
            (self._columns.setdefault(b, len(self._columns)) for b in heard), np.int64, len(heard)
        )
        self._grow_columns(len(self._columns))
        row = self._free_row(cell, survey=owner == SURVEY_OWNER)
        self._serial_next += 1
        serial = self._serial_next
        need = index.room_needed(cols, self._length, self._capacity)
        if self._pool_end + need > self._post_row.size:
            self._grow_pool(self._pool_end + need)
        self._pool_end = index.append(
            cols, gains, row, serial, self._start, self._length, self._capacity,
            self._post_row, self._post_serial, self._post_gain, self._pool_end,
        )  # fmt: skip
        self._serial[row] = serial
        self._t[row] = t_ms
        self._norm[row] = float(gains.astype(float) @ gains.astype(float))
        self._count[row] = cols.size
        self._xy[row] = xy
        self._owner[row] = owner
        self._per_owner[owner] = self._per_owner.get(owner, 0) + 1
        self._live_postings += cols.size
        self._posted += cols.size
        self._cells.setdefault(cell, deque()).append(row)
        self._cell_of[row] = cell
        self._by_age.append((row, serial))
        if len(self._by_age) > 2 * self.params.max_references:  # drop the stale pairs
            self._by_age = deque(p for p in self._by_age if self._serial[p[0]] == p[1])
        if (
            self._posted > STALE_BOUND * self._live_postings + 4
            or self._pool_end > 3 * self._live_postings + 4 * len(self._columns)
        ):
            self._compact()
        return True

    def _free_row(self, cell: tuple[int, int], survey: bool = False) -> int:
        """A row for a new reference in ``cell``: the cell's oldest when the cell is full (for a user's scan,
        its oldest user's scan: a build's scans stay), else a new row while the map is below
        ``max_references``, else the map's oldest."""
        rows = self._cells.get(cell)
        if rows is not None and len(rows) >= self.params.per_cell:
            row = rows[0] if survey else next(r for r in rows if self._owner[r] != SURVEY_OWNER)
        elif self._size < self.params.max_references:
            row = self._size
            self._size += 1
            if row == self._xy.shape[0]:
                self._grow_rows()
            self._cell_of.append(cell)
            return row
        else:
            while True:
                row, serial = self._by_age.popleft()
                if self._serial[row] == serial:
                    break
        self._evict(row)
        return row

    def _evict(self, row: int) -> None:
        """Forget the reference in ``row``: its serial changes when it is reused, so its postings go stale."""
        old = int(self._owner[row])
        self._per_owner[old] -= 1
        if not self._per_owner[old]:
            del self._per_owner[old]
        self._live_postings -= int(self._count[row])
        cell = self._cell_of[row]
        rows = self._cells[cell]
        rows.remove(row)
        if not rows:
            del self._cells[cell]

    def _grow_rows(self) -> None:
        rows = self._xy.shape[0]
        new_rows = min(2 * rows, self.params.max_references)
        for name in ("_xy", "_owner", "_norm", "_count", "_serial", "_t", "_dot", "_shared"):
            old = getattr(self, name)
            fill = -1 if name in ("_owner", "_serial") else 0
            longer = np.full((new_rows, *old.shape[1:]), fill, dtype=old.dtype)
            longer[:rows] = old
            setattr(self, name, longer)

    def _grow_columns(self, n_columns: int) -> None:
        cols = self._start.size
        if n_columns <= cols:
            return
        new_cols = max(2 * cols, n_columns)
        for name in ("_start", "_length", "_capacity"):
            longer = np.zeros(new_cols, dtype=np.int64)
            longer[:cols] = getattr(self, name)
            setattr(self, name, longer)

    def _grow_pool(self, size: int) -> None:
        new_size = max(size, 2 * self._post_row.size)
        for name in ("_post_row", "_post_serial", "_post_gain"):
            old = getattr(self, name)
            longer = np.zeros(new_size, dtype=old.dtype)
            longer[: self._pool_end] = old[: self._pool_end]
            setattr(self, name, longer)

    def _compact(self) -> None:
        """Drop stale postings, and forget the BSSIDs no stored scan hears any more (phones' hotspots and
        randomised MACs would otherwise grow the column index for as long as the server runs)."""
        self._post_row, self._post_serial, self._post_gain, self._pool_end = index.compact(
            self._start, self._length, self._capacity, self._post_row, self._post_serial, self._post_gain,
            self._serial,
        )  # fmt: skip
        self._posted = self._live_postings
        n = len(self._columns)
        kept = np.flatnonzero(self._length[:n] > 0)
        if kept.size == n:
            return
        renumbered = np.full(n, -1, dtype=np.int64)
        renumbered[kept] = np.arange(kept.size)
        self._columns = {b: int(renumbered[c]) for b, c in self._columns.items() if renumbered[c] >= 0}
        for name in ("_start", "_length", "_capacity"):
            column = np.zeros(max(16, kept.size), dtype=np.int64)
            column[: kept.size] = getattr(self, name)[kept]
            setattr(self, name, column)

    def locate(self, owner: int, bssids: list[str], rss: np.ndarray) -> np.ndarray | None:
        """Weighted-kNN position of a scan over the other users' stored scans, or None when the map cannot
        say (too few references, too few APs in common, neighbours too far apart)."""
        return self.locate_many([(owner, bssids, rss)])[0]

    def locate_many(self, queries: list[tuple[int, list[str], np.ndarray]]) -> list[np.ndarray | None]:
        """``locate`` of each (owner, bssids, rss), the map searched by one compiled call for them all."""
        p = self.params
        out: list[np.ndarray | None] = [None] * len(queries)
        asked, cols, gains, counts, norms, owners = [], [], [], [], [], []
        for q, (owner, bssids, rss) in enumerate(queries):
            entries = self._locatable(owner, bssids, rss)
            if entries is None:
                continue
            heard, g = entries
            c, known, norm = self._query(heard, g)
            asked.append(q)
            cols.append(c[known])
            gains.append(g[known])
            counts.append(len(heard))
            norms.append(norm)
            owners.append(owner)
        if not asked:
            return out
        offsets = np.zeros(len(asked) + 1, dtype=np.int64)
        np.cumsum([c.size for c in cols], out=offsets[1:])
        # every argument given: numba dispatches omitted defaults by its slow path
        xy, placed = index.locate_many(
            np.concatenate(cols), np.concatenate(gains), offsets, np.array(norms),
            np.array(counts, dtype=np.int64), np.array(owners, dtype=np.int64), self._start, self._length,
            self._post_row, self._post_serial, self._post_gain, self._serial, self._owner, self._norm,
            self._count, self._dot, self._shared, p.k, self._xy, p.max_spread_m,
        )  # fmt: skip
        for j, q in enumerate(asked):
            if placed[j]:
                out[q] = xy[j].copy()
        return out

    def candidates(
        self, owner: int, bssids: list[str], rss: np.ndarray, max_spread_m: float = math.inf
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The k nearest stored scans in signal space: their positions (k, 2) and kNN weights (1 / distance),
        or None as ``locate``, or when they lie farther apart than ``max_spread_m`` (weighted RMS about their
        kNN position)."""
        found = self._neighbours(owner, bssids, rss)
        if found is None:
            return None
        rows, d = found
        if math.isfinite(max_spread_m) and index.knn_position(self._xy, rows, d)[2] > max_spread_m:
            return None
        return self._xy[rows].copy(), 1.0 / np.maximum(d, 1e-3)

    def _neighbours(
        self, owner: int, bssids: list[str], rss: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The rows of the k nearest other users' scans and their union distances, or None."""
        p = self.params
        entries = self._locatable(owner, bssids, rss)
        if entries is None:
            return None
        heard, gains = entries
        rows, d, candidates = self._search(owner, heard, gains, p.k, 0.0, 0.0, math.inf)
        if candidates < p.k:  # fewer than k references share an AP with the scan
            return None
        return rows, d

    def _locatable(
        self, owner: int, bssids: list[str], rss: np.ndarray
    ) -> tuple[list[str], np.ndarray] | None:
        """A scan's entries (``_gains``) when the map may locate it for ``owner``: at least ``min_aps`` of
        them, and at least ``min_references`` references of other users; else None."""
        p = self.params
        if len(bssids) < p.min_aps:
            return None
        heard, gains = self._gains(bssids, rss)
        if len(heard) < p.min_aps or self._size - self._per_owner.get(owner, 0) < p.min_references:
            return None
        return heard, gains

    def nearby(
        self, owner: int, bssids: list[str], rss: np.ndarray, centre: np.ndarray, radius_m: float, k: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` other users' references within ``radius_m`` of ``centre`` nearest to the scan in signal
        space: their positions (n, 2) and union-fingerprint distances (dB), nearest first; none when the scan
        has fewer than ``min_aps`` or no reference there shares an AP with it. How well this map explains
        the scan there (``slam_core.tracking.floors`` compares it across the floors' maps)."""
        none = (np.zeros((0, 2)), np.zeros(0))
        if len(bssids) < self.params.min_aps or self._size == 0:
            return none
        heard, gains = self._gains(bssids, rss)
        if len(heard) < self.params.min_aps:
            return none
        rows, d, _ = self._search(owner, heard, gains, k, float(centre[0]), float(centre[1]), radius_m)
        return self._xy[rows].copy(), d

    def _query(self, heard: list[str], gains: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """A scan's entries (``_gains``) as the index's columns (-1: an AP no reference heard), which are
        known, and the query's norm (over all of its APs: those no reference heard sit at the floor in every
        reference)."""
        columns = self._columns
        cols = np.fromiter((columns.get(b, -1) for b in heard), np.int64, len(heard))
        g = gains.astype(float)
        return cols, cols >= 0, float(g @ g)

    def _search(
        self, owner: int, heard: list[str], gains: np.ndarray, k: int, cx: float, cy: float, radius_m: float
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """``fingerprint_index.union_nearest`` of a scan's entries (``_gains``) over the index."""
        cols, known, query_norm = self._query(heard, gains)
        # every argument given: numba dispatches omitted defaults by its slow path (+25 % on a batch)
        return index.union_nearest(
            cols[known], gains[known], query_norm, len(heard), owner, self._start, self._length,
            self._post_row, self._post_serial, self._post_gain, self._serial, self._owner, self._norm,
            self._count, self._dot, self._shared, k, self._xy, cx, cy, radius_m,
        )  # fmt: skip

    def fixes_and_places(
        self, users: list[tuple[int, np.ndarray, np.ndarray, list[Scan]]]
    ) -> list[tuple[np.ndarray | None, list[Place]]]:
        """For each user (owner, estimated at ``xy`` with covariance ``cov`` now, with this call's scans in
        time order): the fix (the latest scan the map can place, carried to now by the displacement since
        it) and, when the estimate is confident, the scans to add at ``xy`` less that displacement. Every
        scan is located by one search of the map (``locate_many``). The caller adds the places after all of
        a call's fixes, so users of one call do not locate each other's scans of that call."""
        found = self.locate_many([(owner, s.bssids, s.rss) for owner, _, _, scans in users for s in scans])
        out: list[tuple[np.ndarray | None, list[Place]]] = []
        first = 0
        limit = self.params.max_reference_std_m**2
        for owner, xy, cov, scans in users:
            mine, first = found[first : first + len(scans)], first + len(scans)
            fix = next(
                (
                    f + scan.shift
                    for f, scan in zip(reversed(mine), reversed(scans), strict=True)
                    if f is not None
                ),
                None,
            )
            if largest_eigenvalue2(cov[0, 0], cov[0, 1], cov[1, 1]) > limit:
                out.append((fix, []))
            else:
                out.append((fix, [Place(owner, xy - s.shift, s.bssids, s.rss, s.t_ms) for s in scans]))
        return out
