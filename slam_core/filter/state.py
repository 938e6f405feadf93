"""Filter state as struct-of-arrays over (user slot, particle[, anchor]), with a slot allocator.

Every array's first axis is the user slot. Users come and go: a slot is taken by ``allocate`` and given
back by ``release``; the arrays grow (doubling) when the slots run out. Covariances are stored as
(xx, xy, yy).
"""

from __future__ import annotations

import operator
from dataclasses import dataclass, fields

import numpy as np

from slam_core.filter.kernels import arrays as bundle
from slam_core.filter.kernels.rng import splitmix64

NO_CROWD_ID = -1
_MAP_FIELDS = frozenset({"map_mu", "map_cov", "map_type", "map_count", "map_known", "map_crowd_id"})
"""The per-particle anchor map's arrays, (U, M, K, ...): past a particle's ``map_n`` never read."""
_BUNDLE = operator.attrgetter(*bundle.FIELDS)


@dataclass
class FilterState:
    # per particle
    x: np.ndarray  # (U, M) metres
    y: np.ndarray
    heading: np.ndarray  # (U, M) direction of the last step, rad, counter-clockwise from x (east)
    bias: np.ndarray  # (U, M) heading bias (bias-scale model)
    scale: np.ndarray  # (U, M) step-length scale (bias-scale model)
    walk: np.ndarray  # (U, M) heading random walk (bias-scale model)
    logw: np.ndarray  # (U, M) log weights, normalised (log-sum-exp = 0) after every update
    # per particle anchor map (FastSLAM: each particle its own map)
    map_mu: np.ndarray  # (U, M, K, 2)
    map_cov: np.ndarray  # (U, M, K, 3)
    map_type: np.ndarray  # (U, M, K) int8
    map_count: np.ndarray  # (U, M, K) int32 observations
    map_known: np.ndarray  # (U, M, K) bool, operator-known (exact, never updated)
    map_crowd_id: np.ndarray  # (U, M, K) int64, index in the shared crowd map or NO_CROWD_ID
    map_n: np.ndarray  # (U, M) int32 anchors in use
    # per user
    ctrl_cov: np.ndarray  # (U, 3) covariance of the control data since the last correction (P_t)
    last_obs_heading: np.ndarray  # (U,) last observed step heading (paper model uses its changes)
    rng_key: np.ndarray  # (U,) uint64
    rng_ctr: np.ndarray  # (U,) uint64
    active: np.ndarray  # (U,) bool
    n_resamples: np.ndarray  # (U,) int64
    n_map_overflow: np.ndarray  # (U,) int64
    n_degenerate: np.ndarray  # (U,) int64 updates whose weights all vanished (recovered by resetting)

    @classmethod
    def empty(cls, capacity: int, n_particles: int, map_capacity: int) -> FilterState:
        U, M, K = capacity, n_particles, map_capacity
        return cls(
            x=np.zeros((U, M)),
            y=np.zeros((U, M)),
            heading=np.zeros((U, M)),
            bias=np.zeros((U, M)),
            scale=np.ones((U, M)),
            walk=np.zeros((U, M)),
            logw=np.full((U, M), -np.log(M)),
            map_mu=np.zeros((U, M, K, 2)),
            map_cov=np.zeros((U, M, K, 3)),
            map_type=np.zeros((U, M, K), dtype=np.int8),
            map_count=np.zeros((U, M, K), dtype=np.int32),
            map_known=np.zeros((U, M, K), dtype=np.bool_),
            map_crowd_id=np.full((U, M, K), NO_CROWD_ID, dtype=np.int64),
            map_n=np.zeros((U, M), dtype=np.int32),
            ctrl_cov=np.zeros((U, 3)),
            last_obs_heading=np.full(U, np.nan),
            rng_key=np.zeros(U, dtype=np.uint64),
            rng_ctr=np.zeros(U, dtype=np.uint64),
            active=np.zeros(U, dtype=np.bool_),
            n_resamples=np.zeros(U, dtype=np.int64),
            n_map_overflow=np.zeros(U, dtype=np.int64),
            n_degenerate=np.zeros(U, dtype=np.int64),
        )

    def arrays(self) -> bundle.FilterArrays:
        """The arrays the kernels update, as one tuple (``slam_core.filter.kernels.arrays``)."""
        arrays: bundle.FilterArrays = _BUNDLE(self)
        return arrays

    @property
    def capacity(self) -> int:
        return int(self.x.shape[0])

    @property
    def n_particles(self) -> int:
        return int(self.x.shape[1])

    @property
    def map_capacity(self) -> int:
        return int(self.map_mu.shape[2])

    # Pickled (the server's snapshots) without the unused tail of the particle maps: they have room for
    # map_capacity anchors per particle (grown by use up to 48, ``DynamicSlam._map_room``), so 1,024 user
    # slots x 75 particles can hold ~200 MB however few anchors are in use, which a building would freeze to
    # pickle and compress. Past a particle's map_n nothing is ever read (resampling copies
    # only up to it), so the tail comes back as the empty state's defaults.
    def __getstate__(self) -> dict[str, object]:
        used = int(self.map_n.max()) if self.map_n.size else 0
        state: dict[str, object] = {
            f.name: getattr(self, f.name)[:, :, :used] if f.name in _MAP_FIELDS else getattr(self, f.name)
            for f in fields(self)
        }
        state["map_capacity"] = self.map_capacity
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        map_capacity = state.pop("map_capacity")
        assert isinstance(map_capacity, int)
        self.__dict__.update(state)  # the maps as long as the longest in use, then widened to their room
        self.__dict__.update(self.with_map_capacity(map_capacity).__dict__)

    def with_map_capacity(self, map_capacity: int) -> FilterState:
        """The same state with room for ``map_capacity`` anchors a particle map (at least the current
        room), the new room at the empty state's defaults; the other arrays are shared, not copied."""
        if map_capacity < self.map_capacity:
            raise ValueError("particle maps only grow")
        roomier = FilterState.empty(self.capacity, self.n_particles, map_capacity)
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in _MAP_FIELDS:
                getattr(roomier, f.name)[:, :, : self.map_capacity] = value
            else:
                setattr(roomier, f.name, value)
        return roomier

    def grown(self, capacity: int) -> FilterState:
        """A copy with more user slots; existing slots keep their contents."""
        bigger = FilterState.empty(capacity, self.n_particles, self.map_capacity)
        n = self.capacity
        for f in fields(self):
            getattr(bigger, f.name)[:n] = getattr(self, f.name)
        return bigger


def user_key(seed: int, user_number: int) -> np.uint64:
    """The RNG key of a user: a hash of the filter's seed and the user's admission number."""
    with np.errstate(over="ignore"):
        return np.uint64(splitmix64(np.uint64(seed) * np.uint64(0x100000001B3) ^ np.uint64(user_number)))


class SlotAllocator:
    """Hands out user slots, lowest free first; grows by doubling."""

    def __init__(self, capacity: int) -> None:
        self._free = list(range(capacity - 1, -1, -1))
        self._capacity = capacity

    def allocate(self) -> tuple[int, int | None]:
        """A free slot, and the new capacity if the arrays must grow first."""
        grow_to = None
        if not self._free:
            grow_to = max(1, self._capacity * 2)
            self._free = list(range(grow_to - 1, self._capacity - 1, -1))
            self._capacity = grow_to
        return self._free.pop(), grow_to

    def release(self, slot: int) -> None:
        if slot in self._free or not 0 <= slot < self._capacity:
            raise ValueError(f"slot {slot} is not allocated")
        self._free.append(slot)
        self._free.sort(reverse=True)
