"""The tracker's bookkeeping per user (its dead-reckoned trail) and per round of engine calls."""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass, field

import numpy as np

TRAIL_MS = 30_000
"""How far back each user's dead-reckoned path is kept (a detection reported after its peak looks back)."""


CARRY_DRIFT = 0.1
"""Dead reckoning's error per metre walked (PDR drifts ~10-13 % of the distance on the real walks): the
standard deviation given to an observation carried from its time to now along the user's own steps."""


def carry_variance(walked_m: np.ndarray | float) -> np.ndarray:
    """Variance (m^2) of a position carried over ``walked_m`` metres of the user's own dead reckoning."""
    return np.square(CARRY_DRIFT * np.asarray(walked_m, dtype=np.float64))


@dataclass
class UserTrack:
    number: int = -1  # start order: the crowd graph's user id
    slot: int = -1
    last_t_ms: int = -1
    heading: float = math.nan  # counter-clockwise from east, of the last step
    displacement: np.ndarray = field(default_factory=lambda: np.zeros(2))
    walked: float = 0.0
    origin: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))  # the starting fix
    gyro_displacement: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """The steps walked since the fix along their directions without the front-end's north offset."""
    heading_offset: float = math.nan  # the front-end's latest north offset (clockwise), NaN: none
    since_gyro: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """``gyro_displacement`` since the last absolute observation (fix, anchor): what a revision turns."""
    since_laid: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """What the filter was moved by since then (steps as sent, plus earlier revisions)."""
    trail: array[float] = field(default_factory=lambda: array("d"))
    """Recent steps, four numbers each: time (ms, exact in a double), displacement x and y after it, distance
    walked after it. A flat array of doubles: the garbage collector does not walk it and a snapshot writes
    it as one block (a list of small tuples and lists had cost a 1,000-user building ~100,000 objects in
    every full collection and ~75 ms of pickling in the building's thread)."""

    # A user travels in a snapshot as one flat tuple, its fields in declaration order and its 2-vectors as
    # plain floats: thousands of tiny arrays, or of dicts naming every field, pickle slowly one by one (a
    # dict per user had been ~9 ms of a 2,000-user snapshot, pickled in the building's thread).
    _VECTORS = ("displacement", "origin", "gyro_displacement", "since_gyro", "since_laid")

    def __getstate__(self) -> tuple[object, ...]:
        d, o, g = self.displacement, self.origin, self.gyro_displacement
        sg, sl = self.since_gyro, self.since_laid
        return (
            self.number, self.slot, self.last_t_ms, self.heading, self.walked, self.heading_offset,
            self.trail, float(d[0]), float(d[1]), float(o[0]), float(o[1]), float(g[0]), float(g[1]),
            float(sg[0]), float(sg[1]), float(sl[0]), float(sl[1]),
        )  # fmt: skip

    def __setstate__(self, state: tuple[object, ...] | dict[str, object]) -> None:
        if isinstance(state, dict):  # written before the flat tuple: field names, 2-vectors as tuples
            self.__dict__.update(state)
            for name in self._VECTORS:
                self.__dict__[name] = np.array(state[name], dtype=np.float64)
            return
        (
            self.number, self.slot, self.last_t_ms, self.heading, self.walked, self.heading_offset,
            self.trail, dx, dy, ox, oy, gx, gy, sgx, sgy, slx, sly,
        ) = state  # type: ignore[assignment]  # fmt: skip
        self.displacement = np.array([dx, dy])
        self.origin = np.array([ox, oy])
        self.gyro_displacement = np.array([gx, gy])
        self.since_gyro = np.array([sgx, sgy])
        self.since_laid = np.array([slx, sly])

    def lay(
        self,
        times: list[int],
        dx: list[float],
        dy: list[float],
        lengths: list[float],
        laid: tuple[float, float],
        gyro: tuple[float, float],
        heading_offset: float,
    ) -> None:
        """Add steps (their displacements ``dx``, ``dy`` along the headings applied, and their sum ``laid``;
        ``gyro``: their sum with the front-end's north offset taken back out) to the dead-reckoned path and
        its trail. ``heading_offset``: the latest offset the steps carried (NaN: none)."""
        x, y = float(self.displacement[0]), float(self.displacement[1])
        cx = cy = walked = 0.0
        for t, ddx, ddy, length in zip(times, dx, dy, lengths, strict=True):
            cx += ddx  # sequential, as a cumulative sum from the last step's position
            cy += ddy
            walked += length
            self.trail.extend((t, x + cx, y + cy, self.walked + walked))
        trail, horizon = self.trail, times[-1] - TRAIL_MS
        old = 0
        while old < len(trail) and trail[old] < horizon:
            old += 4
        del trail[:old]
        self.displacement = np.array(trail[-3:-1])
        self.walked = trail[-1]
        self.gyro_displacement = self.gyro_displacement + gyro
        self.since_gyro = self.since_gyro + gyro
        self.since_laid = self.since_laid + laid
        if math.isfinite(heading_offset):
            self.heading_offset = heading_offset

    def revision(self) -> np.ndarray:
        """How far the path since the last absolute observation moves when all of it takes the latest north
        offset (zero without one); counted as laid."""
        if not math.isfinite(self.heading_offset):
            return np.zeros(2)
        c, s = math.cos(self.heading_offset), math.sin(self.heading_offset)
        gx, gy = self.since_gyro  # a clockwise azimuth offset turns the relative path clockwise
        shift: np.ndarray = np.array([c * gx + s * gy, -s * gx + c * gy]) - self.since_laid
        self.since_laid = self.since_laid + shift
        return shift

    def pin(self) -> None:
        """An absolute observation was applied: the path before it is no longer the filter's to revise."""
        self.since_gyro = np.zeros(2)
        self.since_laid = np.zeros(2)

    def at(self, t_ms: int) -> tuple[np.ndarray, float]:
        """Dead-reckoned displacement and distance walked at ``t_ms`` (its last step then; the oldest kept
        when older than the trail)."""
        displacement, walked = trail_lookup([self], np.zeros(1, np.int64), np.array([t_ms], np.int64))
        return displacement[0], float(walked[0])


_SEGMENT = np.int64(1) << np.int64(41)
"""Users' trails searched at once are told apart by multiples of 2^41 ms (~70 years) added to the times."""


def trail_lookup(
    tracks: list[UserTrack], which: np.ndarray, t_ms: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``UserTrack.at`` of user ``tracks[which[i]]`` at ``t_ms[i]`` for every i: (n, 2) displacements and
    (n,) distances walked. One search over all the users' trails at once: a pass per user had cost ~30 us,
    13 ms a call for the encounters of a 2,000-phone building."""
    which = np.asarray(which, dtype=np.int64)
    t = np.asarray(t_ms, dtype=np.int64)
    displacement = np.array([u.displacement for u in tracks], dtype=np.float64).reshape(-1, 2)[which]
    walked = np.array([u.walked for u in tracks], dtype=np.float64)[which]
    sizes = np.array([len(u.trail) // 4 for u in tracks], dtype=np.int64)
    if not which.size or not sizes.any():
        return displacement, walked
    last = np.array([u.last_t_ms for u in tracks], dtype=np.int64)[which]
    # frombuffer's views only live inside the concatenation: a trail exporting its buffer cannot grow
    trail = np.concatenate([np.frombuffer(u.trail, dtype=np.float64) for u in tracks if u.trail]).reshape(
        -1, 4
    )
    trail_t = trail[:, 0].astype(np.int64)
    base = min(int(trail_t.min()), int(t.min()))
    segment = np.repeat(np.arange(sizes.size, dtype=np.int64), sizes)
    start = np.cumsum(sizes) - sizes  # each user's first row
    k = (
        np.searchsorted(segment * _SEGMENT + (trail_t - base), which * _SEGMENT + (t - base), side="right")
        - 1
    )
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
    tracks: list[UserTrack], which: np.ndarray, t_ms: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From ``t_ms[i]`` to now along user ``tracks[which[i]]``'s own steps: (n, 2) displacement, (n,) the
    distance walked (``carry_variance`` gives the carry's variance), and (n,) whether the time can be placed
    at all (the user's trail reaches back to it). Only users with steps after a time are searched."""
    which = np.asarray(which, dtype=np.int64)
    t = np.asarray(t_ms, dtype=np.int64)
    last = np.array([u.last_t_ms for u in tracks], dtype=np.int64)[which]
    shift, walked = np.zeros((t.size, 2)), np.zeros(t.size)
    behind = np.flatnonzero(t < last)
    if behind.size:
        walkers, local = np.unique(which[behind], return_inverse=True)
        moved = [tracks[w] for w in walkers.tolist()]
        then, walked_then = trail_lookup(moved, local, t[behind])
        now = np.array([u.displacement for u in moved], dtype=np.float64)[local]
        walked_now = np.array([u.walked for u in moved], dtype=np.float64)[local]
        shift[behind] = now - then
        walked[behind] = walked_now - walked_then
    return shift, walked, t >= last - TRAIL_MS


@dataclass
class Round:
    users: list[str] = field(default_factory=list)
    step_len: list[np.ndarray] = field(default_factory=list)
    step_head: list[np.ndarray] = field(default_factory=list)
    det_users: list[str] = field(default_factory=list)
    det_types: list[int] = field(default_factory=list)
    det_t: list[int] = field(default_factory=list)
    det_signature: list[str] = field(default_factory=list)
    fix_users: list[str] = field(default_factory=list)
    fix_xy: list[np.ndarray] = field(default_factory=list)
    fix_sigma: list[float] = field(default_factory=list)

    step_t: list[np.ndarray] = field(default_factory=list)
    step_offset: list[np.ndarray] = field(default_factory=list)
    det_observed_t: list[int] = field(default_factory=list)

    def add_steps(
        self, user: str, lengths: list[float], headings: list[float], times: list[int], offsets: list[float]
    ) -> None:
        self.users.append(user)
        self.step_offset.append(np.array(offsets))
        self.step_len.append(np.array(lengths))
        self.step_head.append(np.array(headings))
        self.step_t.append(np.array(times, dtype=np.int64))


def lay_steps(users: list[UserTrack], rnd: Round, lengths: np.ndarray, headings: np.ndarray) -> None:
    """Every user's steps of a round (``lengths`` and ``headings``: the round's, concatenated) on its
    dead-reckoned path: the trigonometry of all users' steps in one array pass (a Python pass per user had
    cost more than the engine's motion update)."""
    counts = [x.size for x in rnd.step_len]
    offsets = np.concatenate(rnd.step_offset)
    relative = headings + np.nan_to_num(offsets)  # counter-clockwise headings, the clockwise offset taken out
    parts = np.stack(
        [
            lengths * np.cos(headings),
            lengths * np.sin(headings),
            lengths * np.cos(relative),
            lengths * np.sin(relative),
        ]
    )
    starts = np.cumsum([0, *counts[:-1]])
    sums = np.add.reduceat(parts, starts, axis=1).T.tolist()
    dx, dy = parts[0].tolist(), parts[1].tolist()
    length_list = lengths.tolist()
    times = np.concatenate(rnd.step_t).tolist()
    finite = np.isfinite(offsets)
    last_finite = np.maximum.accumulate(np.where(finite, np.arange(offsets.size), -1))
    end = 0
    for u, n, (lx, ly, gx, gy) in zip(users, counts, sums, strict=True):
        start, end = end, end + n
        k = int(last_finite[end - 1])
        u.lay(
            times[start:end],
            dx[start:end],
            dy[start:end],
            length_list[start:end],
            (lx, ly),
            (gx, gy),
            float(offsets[k]) if k >= start else math.nan,
        )


def round_at(rounds: list[Round], r: int) -> Round:
    while len(rounds) <= r:
        rounds.append(Round())
    return rounds[r]
