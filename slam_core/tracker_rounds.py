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


VELOCITY_WINDOW_MS = 2_000
"""A user's recent velocity is its dead-reckoned displacement over its last two seconds of steps."""
MAX_SPEED_M_PER_MS = 0.003
"""3 m/s: no pedestrian is extrapolated faster (a run; walking is ~1.4 m/s), which also bounds how far any
user can be guessed to have gone in a given time."""


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
    velocity_x: float = 0.0
    velocity_y: float = 0.0
    """The dead-reckoned velocity over the ``VELOCITY_WINDOW_MS`` before the last step (m per ms, at most
    ``MAX_SPEED_M_PER_MS``), kept by ``lay``: how ``SlotColumns.extrapolated`` guesses an unheard user."""

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
            float(sg[0]), float(sg[1]), float(sl[0]), float(sl[1]), self.velocity_x, self.velocity_y,
        )  # fmt: skip

    def __setstate__(self, state: tuple[object, ...] | dict[str, object]) -> None:
        if isinstance(state, dict):  # written before the flat tuple: field names, 2-vectors as tuples
            self.__dict__.update(state)
            for name in self._VECTORS:
                self.__dict__[name] = np.array(state[name], dtype=np.float64)
            self.velocity_x, self.velocity_y = self._recent_velocity()
            return
        (
            self.number, self.slot, self.last_t_ms, self.heading, self.walked, self.heading_offset,
            self.trail, dx, dy, ox, oy, gx, gy, sgx, sgy, slx, sly, self.velocity_x, self.velocity_y,
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
        self.velocity_x, self.velocity_y = self._recent_velocity()
        self.gyro_displacement = self.gyro_displacement + gyro
        self.since_gyro = self.since_gyro + gyro
        self.since_laid = self.since_laid + laid
        if math.isfinite(heading_offset):
            self.heading_offset = heading_offset

    def _recent_velocity(self) -> tuple[float, float]:
        """Displacement from the last step at least ``VELOCITY_WINDOW_MS`` before the latest one (the oldest
        kept when the trail is shorter) to the latest, over that window, capped at ``MAX_SPEED_M_PER_MS``."""
        trail = self.trail
        if not trail:
            return 0.0, 0.0
        horizon = trail[-4] - VELOCITY_WINDOW_MS
        i = len(trail) - 4
        while i > 0 and trail[i] > horizon:
            i -= 4
        vx = (trail[-3] - trail[i + 1]) / VELOCITY_WINDOW_MS
        vy = (trail[-2] - trail[i + 2]) / VELOCITY_WINDOW_MS
        speed = math.hypot(vx, vy)
        if speed > MAX_SPEED_M_PER_MS:
            vx, vy = vx * MAX_SPEED_M_PER_MS / speed, vy * MAX_SPEED_M_PER_MS / speed
        return vx, vy

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
        one = TrackTable.of([self])
        displacement, walked = trail_lookup(one, np.zeros(1, np.int64), np.array([t_ms], np.int64))
        return displacement[0], float(walked[0])


@dataclass(frozen=True)
class TrackTable:
    """Some users' tracks with the columns the vectorised lookups below need, read once per call (a list
    comprehension per column per lookup had made them cost as much as the arithmetic)."""

    tracks: list[UserTrack]
    last_t_ms: np.ndarray  # (n,) int64
    walked: np.ndarray  # (n,)
    displacement: np.ndarray  # (n, 2)
    velocity: np.ndarray  # (n, 2) m per ms

    @classmethod
    def of(cls, tracks: list[UserTrack]) -> TrackTable:
        rows = np.array(
            [(u.last_t_ms, u.walked, *u.displacement.tolist(), u.velocity_x, u.velocity_y) for u in tracks],
            dtype=np.float64,
        ).reshape(-1, 6)  # epoch ms are exact in a double
        return cls(tracks, rows[:, 0].astype(np.int64), rows[:, 1], rows[:, 2:4], rows[:, 4:6])

    def subset(self, index: np.ndarray) -> TrackTable:
        return TrackTable(
            [self.tracks[i] for i in index.tolist()],
            self.last_t_ms[index],
            self.walked[index],
            self.displacement[index],
            self.velocity[index],
        )


_SEGMENT = np.int64(1) << np.int64(41)
"""Users' trails searched at once are told apart by multiples of 2^41 ms (~70 years) added to the times."""


def trail_lookup(table: TrackTable, which: np.ndarray, t_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``UserTrack.at`` of user ``which[i]`` of the table at ``t_ms[i]`` for every i: (n, 2) displacements
    and (n,) distances walked. One search over all the table's trails at once: a pass per user had cost
    ~30 us, 13 ms a call for the encounters of a 2,000-phone building."""
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


MAX_EXTRAPOLATION_MS = 5_000
"""A user not heard from for longer than this is not guessed at: where it went is anyone's guess."""
STANDING_MS = 1_500
"""A phone that reports this long past its last step (a walker steps every ~0.5 s) is standing still."""
_NEVER = np.iinfo(np.int64).min


class SlotColumns:
    """Per filter slot, the few numbers of each tracked user's track that choosing encounters reads for every
    reading of a call (~12,000 from ~1,100 users at 2,000 phones): kept as arrays and updated for the users
    of each call, since reading them off the tracks, one Python object each, had cost more than the choice.
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
            self.velocity[u.slot] = (u.velocity_x, u.velocity_y) if walking else (0.0, 0.0)

    def reach(self, slots: np.ndarray, t_ms: np.ndarray) -> np.ndarray:
        """At least how far each user walked after ``t_ms``: 0 when it has not reported past it, its latest
        batch's walk when the time is within that batch, infinity (unknown) when older."""
        t = np.asarray(t_ms, dtype=np.int64)
        latest_batch = self.walked[slots] - self.start_walked[slots]
        bound = np.where(t >= self.start_t_ms[slots], latest_batch, np.inf)
        result: np.ndarray = np.where(t >= self.last_t_ms[slots], 0.0, bound)
        return result

    def extrapolated(self, slots: np.ndarray, t_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where each user has gone from its phone's last report to ``t_ms``, a time it has not reported
        yet, at its recent velocity (``UserTrack.velocity_x``, ``velocity_y``; zero for a user standing at
        its last report): (n, 2) displacement (zero when the time has been reported); (n,) the variance of
        that guess, (half its length)^2 (the user may have stopped or turned); and (n,) whether it is
        guessed at all (not after ``MAX_EXTRAPOLATION_MS`` of silence)."""
        silence = np.asarray(t_ms, dtype=np.int64) - self.heard_t_ms[slots]
        ahead = self.velocity[slots] * np.maximum(silence, 0).astype(np.float64)[:, None]
        return ahead, 0.25 * np.sum(ahead * ahead, axis=1), silence <= MAX_EXTRAPOLATION_MS


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
