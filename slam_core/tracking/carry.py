"""Readings carried in time on the tracker's users: back along a user's own steps to now (``carried_since``,
over many users' trails in one search), or, for a user whose phone has not reported up to a reading yet,
guessed ahead at its recent velocity (``SlotColumns``). Pure numerics."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from slam_core.tracking.trails import TRAIL_MS

if TYPE_CHECKING:
    from slam_core.tracking.trails import UserTrack

CARRY_DRIFT = 0.1
"""Dead reckoning's error per metre walked (PDR drifts ~10-13 % of the distance on the real walks): the
standard deviation given to an observation carried from its time to now along the user's own steps."""


def carry_variance(walked_m: np.ndarray | float) -> np.ndarray:
    """Variance (m^2) of a position carried over ``walked_m`` metres of the user's own dead reckoning."""
    return np.square(CARRY_DRIFT * np.asarray(walked_m, dtype=np.float64))


@dataclass(frozen=True)
class TrackTable:
    """Some users' tracks with the columns the vectorised lookups below need, read once per call rather
    than once per lookup."""

    tracks: list[UserTrack]
    last_t_ms: np.ndarray  # (n,) int64
    walked: np.ndarray  # (n,)
    displacement: np.ndarray  # (n, 2)

    @classmethod
    def of(cls, tracks: list[UserTrack]) -> TrackTable:
        rows = np.array(
            [(u.last_t_ms, u.walked, *u.displacement.tolist()) for u in tracks], dtype=np.float64
        ).reshape(-1, 4)  # epoch ms are exact in a double
        return cls(tracks, rows[:, 0].astype(np.int64), rows[:, 1], rows[:, 2:4])

    def subset(self, index: np.ndarray) -> TrackTable:
        return TrackTable(
            [self.tracks[i] for i in index.tolist()],
            self.last_t_ms[index],
            self.walked[index],
            self.displacement[index],
        )


_SEGMENT = np.int64(1) << np.int64(41)
"""Users' trails searched at once are told apart by multiples of 2^41 ms (~70 years) added to the times."""


def trail_lookup(table: TrackTable, which: np.ndarray, t_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dead-reckoned displacement and distance walked of user ``which[i]`` of the table at ``t_ms[i]`` (its
    last step then; the oldest kept when older than its trail; where it is now when after its last step),
    for every i: (n, 2) displacements and (n,) distances walked. One search over all the table's trails at
    once, not a pass per user: a busy call carries readings of hundreds of users."""
    which = np.asarray(which, dtype=np.int64)
    t = np.asarray(t_ms, dtype=np.int64)
    displacement = table.displacement[which]
    walked = table.walked[which]
    sizes = np.array([len(u.trail) // 4 for u in table.tracks], dtype=np.int64)
    if not which.size or not sizes.any():
        return displacement, walked
    last = table.last_t_ms[which]
    # frombuffer's views only live inside the concatenation: a trail exporting its buffer cannot grow
    parts = [np.frombuffer(u.trail, dtype=np.float64) for u in table.tracks if u.trail]
    trail = np.concatenate(parts).reshape(-1, 4)
    del parts
    trail_t = trail[:, 0].astype(np.int64)
    base = min(int(trail_t.min()), int(t.min()))
    segment = np.repeat(np.arange(sizes.size, dtype=np.int64), sizes)
    start = np.cumsum(sizes) - sizes  # each user's first row
    keys = segment * _SEGMENT + (trail_t - base)
    k = np.searchsorted(keys, which * _SEGMENT + (t - base), side="right") - 1
    own = start[which]
    has_trail = sizes[which] > 0
    in_trail = has_trail & (k >= own)
    # before the oldest step kept: that step, unless the time is past the user's last one anyway
    use = in_trail | (has_trail & (t < last))
    rows = np.where(in_trail, k, own)[use]
    displacement[use] = trail[rows, 1:3]
    walked[use] = trail[rows, 3]
    return displacement, walked


def carried_since(
    table: TrackTable, which: np.ndarray, t_ms: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From ``t_ms[i]`` to now along user ``which[i]``'s own steps: (n, 2) displacement, (n,) the distance
    walked (``carry_variance`` gives the carry's variance), and (n,) whether the time can be placed at all
    (the user's trail reaches back to it). Only users with steps after a time are searched."""
    which = np.asarray(which, dtype=np.int64)
    t = np.asarray(t_ms, dtype=np.int64)
    last = table.last_t_ms[which]
    shift, walked = np.zeros((t.size, 2)), np.zeros(t.size)
    behind = np.flatnonzero(t < last)
    if behind.size:
        walkers, local = np.unique(which[behind], return_inverse=True)
        moved = table.subset(walkers)
        then, walked_then = trail_lookup(moved, local, t[behind])
        shift[behind] = moved.displacement[local] - then
        walked[behind] = moved.walked[local] - walked_then
    return shift, walked, t >= last - TRAIL_MS


GUESS_SIGMA_FRACTION = 0.5
"""A user guessed ahead may have stopped or turned: the guess's sigma is half its length."""


def guess_variance(ahead: np.ndarray) -> np.ndarray:
    """Variance (m^2) of guessed displacements ``ahead`` (..., 2)."""
    variance: np.ndarray = GUESS_SIGMA_FRACTION**2 * np.sum(ahead * ahead, axis=-1)
    return variance


MAX_EXTRAPOLATION_MS = 5_000
"""A user not heard from for longer than this is not guessed at: where it went is anyone's guess."""
STANDING_MS = 1_500
"""A phone that reports this long past its last step (a walker steps every ~0.5 s) is standing still."""
_NEVER = np.iinfo(np.int64).min


class SlotColumns:
    """Per filter slot, the few numbers of each tracked user's track that choosing encounters reads for every
    reading of a call (thousands in a busy building): kept as arrays and updated for the users of each call,
    rather than read off the tracks, one Python object each, for every reading.
    ``start_t_ms`` and ``start_walked``: the user's last event and distance walked before its latest batch
    (never and 0 for a user new since), which bound how far it walked after any later time; ``heard_t_ms``:
    the latest time its phone has reported anything at all (a scan, a sighting), up to which a user without
    steps since its last one stood still."""

    def __init__(self) -> None:
        self.heard_t_ms = np.zeros(0, dtype=np.int64)
        self.last_t_ms = np.zeros(0, dtype=np.int64)
        self.walked = np.zeros(0)
        self.velocity = np.zeros((0, 2))
        self.start_t_ms = np.zeros(0, dtype=np.int64)
        self.start_walked = np.zeros(0)

    def _room(self, slot: int) -> None:
        n = self.last_t_ms.size
        if slot < n:
            return
        grow = max(slot + 1, 2 * n) - n
        self.heard_t_ms = np.concatenate([self.heard_t_ms, np.full(grow, -1, dtype=np.int64)])
        self.last_t_ms = np.concatenate([self.last_t_ms, np.full(grow, -1, dtype=np.int64)])
        self.walked = np.concatenate([self.walked, np.zeros(grow)])
        self.velocity = np.concatenate([self.velocity, np.zeros((grow, 2))])
        self.start_t_ms = np.concatenate([self.start_t_ms, np.full(grow, _NEVER, dtype=np.int64)])
        self.start_walked = np.concatenate([self.start_walked, np.zeros(grow)])

    def reset(self, slot: int) -> None:
        """A user starts in this slot."""
        self._room(slot)
        self.heard_t_ms[slot], self.last_t_ms[slot], self.walked[slot], self.velocity[slot] = -1, -1, 0.0, 0.0
        self.start_t_ms[slot], self.start_walked[slot] = _NEVER, 0.0

    def begin(self, tracks: list[UserTrack]) -> None:
        """Before a call's events: its tracked users' reports so far."""
        for u in tracks:
            if u.slot >= 0:
                self._room(u.slot)
                self.start_t_ms[u.slot], self.start_walked[u.slot] = u.last_t_ms, u.walked

    def update(self, tracks: list[UserTrack], heard_t_ms: list[int]) -> None:
        """After a call's events: its tracked users as they are now, each heard up to ``heard_t_ms`` (its
        batch's latest time of anything)."""
        for u, heard in zip(tracks, heard_t_ms, strict=True):
            if u.slot < 0:
                continue
            self._room(u.slot)
            heard = max(heard, u.last_t_ms, int(self.heard_t_ms[u.slot]))
            self.heard_t_ms[u.slot], self.last_t_ms[u.slot], self.walked[u.slot] = (
                heard,
                u.last_t_ms,
                u.walked,
            )
            walking = bool(u.trail) and heard - u.trail[-4] <= STANDING_MS
            self.velocity[u.slot] = u.recent_velocity() if walking else (0.0, 0.0)

    def reach(self, slots: np.ndarray, t_ms: np.ndarray) -> np.ndarray:
        """A bound on how far each user walked after ``t_ms`` (at least that far): 0 when it has not reported
        steps past it, its latest batch's walk when the time is within that batch, infinity (unknown) when
        older."""
        t = np.asarray(t_ms, dtype=np.int64)
        latest_batch = self.walked[slots] - self.start_walked[slots]
        bound = np.where(t >= self.start_t_ms[slots], latest_batch, np.inf)
        result: np.ndarray = np.where(t >= self.last_t_ms[slots], 0.0, bound)
        return result

    def extrapolated(self, slots: np.ndarray, t_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where each user has gone from its phone's last report to ``t_ms``, a time it has not reported
        yet, at its recent velocity (``UserTrack.recent_velocity``; zero for a user standing at its last
        report): (n, 2) displacement (zero when the time has been reported); (n,) the variance of that guess
        (``guess_variance``); and (n,) whether it is guessed at all (not after ``MAX_EXTRAPOLATION_MS`` of
        silence)."""
        silence = np.asarray(t_ms, dtype=np.int64) - self.heard_t_ms[slots]
        ahead = self.velocity[slots] * np.maximum(silence, 0).astype(np.float64)[:, None]
        return ahead, guess_variance(ahead), silence <= MAX_EXTRAPOLATION_MS
