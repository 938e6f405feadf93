"""Each tracked user's dead-reckoned trail: the path its steps laid since it started, kept ``TRAIL_MS``
back, for placing readings in time (``slam_core.tracking.carry``). The trails are kept by filter slot in one
pool of rows (``Trails``), which compiled lookups search for many users at once."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

TRAIL_MS = 30_000
"""How far back each user's dead-reckoned path is kept (a detection reported after its peak looks back)."""


VELOCITY_WINDOW_MS = 2_000
"""A user's recent velocity is its dead-reckoned displacement over its last two seconds of steps."""
MAX_SPEED_M_PER_MS = 0.003
"""3 m/s: no pedestrian is extrapolated faster (a run; walking is ~1.4 m/s), which also bounds how far any
user can be guessed to have gone in a given time."""


def cap_speed(vx: float, vy: float, limit: float = MAX_SPEED_M_PER_MS) -> tuple[float, float]:
    """The velocity, slowed to ``limit`` (in its units) if faster."""
    speed = math.hypot(vx, vy)
    if speed > limit:
        return vx * limit / speed, vy * limit / speed
    return vx, vy


@dataclass
class UserTrack:
    number: int = -1  # start order: the crowd graph's user id
    slot: int = -1
    placed: bool = True
    """False while a user started without a fix is still spread over its candidate places."""
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

    # A user travels in a snapshot as one flat tuple, its fields in declaration order and its 2-vectors as
    # plain floats: thousands of tiny arrays, or of dicts naming every field, pickle slowly one by one, in
    # the building's thread.

    def __getstate__(self) -> tuple[object, ...]:
        d, o, g = self.displacement, self.origin, self.gyro_displacement
        sg, sl = self.since_gyro, self.since_laid
        return (
            self.number, self.slot, self.last_t_ms, self.heading, self.walked, self.heading_offset,
            float(d[0]), float(d[1]), float(o[0]), float(o[1]), float(g[0]), float(g[1]),
            float(sg[0]), float(sg[1]), float(sl[0]), float(sl[1]), self.placed,
        )  # fmt: skip

    def __setstate__(self, state: tuple[object, ...]) -> None:
        (
            self.number, self.slot, self.last_t_ms, self.heading, self.walked, self.heading_offset,
            dx, dy, ox, oy, gx, gy, sgx, sgy, slx, sly, self.placed,
        ) = state  # type: ignore[assignment]  # fmt: skip
        self.displacement = np.array([dx, dy])
        self.origin = np.array([ox, oy])
        self.gyro_displacement = np.array([gx, gy])
        self.since_gyro = np.array([sgx, sgy])
        self.since_laid = np.array([slx, sly])

    def lay(
        self,
        trails: Trails,
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
        to its trail in ``trails`` (at the user's slot). ``heading_offset``: the latest offset the steps
        carried (NaN: none)."""
        x, y = float(self.displacement[0]), float(self.displacement[1])
        cx = cy = walked = 0.0
        rows: list[float] = []
        for t, ddx, ddy, length in zip(times, dx, dy, lengths, strict=True):
            cx += ddx  # sequential, as a cumulative sum from the last step's position
            cy += ddy
            walked += length
            rows += (t, x + cx, y + cy, self.walked + walked)
        trails.lay(self.slot, rows, times[-1] - TRAIL_MS)
        self.displacement = np.array(rows[-3:-1])
        self.walked = rows[-1]
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


class Trails:
    """Every tracked user's recent steps, by filter slot: each step a row (time in ms, exact in a double;
    displacement x and y after it; distance walked after it), a slot's rows a block of one pool, oldest
    first. Arrays only: the garbage collector does not walk them, a snapshot writes each as one block, and
    one compiled call searches the trails of a whole call's users (``slam_core.tracking.carry``)."""

    def __init__(self) -> None:
        self.rows = np.zeros((256, 4))
        self.start = np.zeros(0, dtype=np.int64)
        self.length = np.zeros(0, dtype=np.int64)
        self.capacity = np.zeros(0, dtype=np.int64)
        self.used = 0  # rows of the pool handed out to blocks

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        state["rows"] = self.rows[: self.used]  # the pool's free tail is not written
        return state

    def reset(self, slot: int) -> None:
        """The user in this slot starts a new trail (a new user, or its timeline restarted)."""
        self._room(slot)
        self.length[slot] = 0

    def release(self, slot: int) -> None:
        """The slot is freed: its block goes back to the pool at the next compaction."""
        if slot < self.length.size:
            self.length[slot] = 0
            self.capacity[slot] = 0

    def lay(self, slot: int, rows: list[float], horizon_ms: int) -> None:
        """Append steps (``rows``: four numbers a step, in time order) and drop the steps before
        ``horizon_ms`` from the front."""
        self._room(slot)
        new = len(rows) // 4
        if self.length[slot] + new > self.capacity[slot]:
            self._move(slot, max(int(self.length[slot]) + new, 2 * int(self.capacity[slot]), 8))
        _lay(self.rows, self.start, self.length, slot, np.array(rows).reshape(-1, 4), horizon_ms)

    def of(self, slot: int) -> np.ndarray:
        """The slot's rows (a view: read it before the trails change)."""
        if slot >= self.length.size:
            return self.rows[:0]
        begin = int(self.start[slot])
        rows: np.ndarray = self.rows[begin : begin + int(self.length[slot])]
        return rows

    def last_step_ms(self, slot: int) -> float | None:
        """The time of the slot's last step kept, None without one."""
        if slot >= self.length.size or self.length[slot] == 0:
            return None
        return float(self.rows[self.start[slot] + self.length[slot] - 1, 0])

    def recent_velocity(self, slot: int) -> tuple[float, float]:
        """Dead-reckoned velocity (m per ms): the displacement from the last step at least
        ``VELOCITY_WINDOW_MS`` before the latest one (the oldest kept when the trail is shorter) to the
        latest, over that window, capped at ``MAX_SPEED_M_PER_MS``; how ``SlotColumns.extrapolated`` guesses
        a user not heard yet."""
        rows = self.of(slot)
        if not rows.shape[0]:
            return 0.0, 0.0
        last = rows.shape[0] - 1
        horizon = float(rows[last, 0]) - VELOCITY_WINDOW_MS
        i = last
        while i > 0 and rows[i, 0] > horizon:
            i -= 1
        vx = (float(rows[last, 1]) - float(rows[i, 1])) / VELOCITY_WINDOW_MS
        vy = (float(rows[last, 2]) - float(rows[i, 2])) / VELOCITY_WINDOW_MS
        return cap_speed(vx, vy)

    def _room(self, slot: int) -> None:
        n = self.length.size
        if slot < n:
            return
        grow = max(slot + 1, 2 * n) - n
        self.start = np.concatenate([self.start, np.zeros(grow, dtype=np.int64)])
        self.length = np.concatenate([self.length, np.zeros(grow, dtype=np.int64)])
        self.capacity = np.concatenate([self.capacity, np.zeros(grow, dtype=np.int64)])

    def _move(self, slot: int, capacity: int) -> None:
        """Give the slot a block of ``capacity`` rows at the end of the pool (its old block becomes waste that
        the next compaction reclaims)."""
        if self.used + capacity > self.rows.shape[0]:
            self._compact(capacity)
        begin, n = int(self.start[slot]), int(self.length[slot])
        self.rows[self.used : self.used + n] = self.rows[begin : begin + n]
        self.start[slot], self.capacity[slot] = self.used, capacity
        self.used += capacity

    def _compact(self, more: int) -> None:
        """The live blocks packed at the front of a pool with room for ``more`` rows after them (twice what
        they take, so that a compaction is rare)."""
        live = np.flatnonzero(self.capacity > 0)
        needed = int(self.capacity[live].sum()) + more
        size = max(256, self.rows.shape[0] if needed <= self.rows.shape[0] // 2 else 2 * needed)
        rows = np.zeros((size, 4))
        at = 0
        for slot in live.tolist():
            begin, n = int(self.start[slot]), int(self.length[slot])
            rows[at : at + n] = self.rows[begin : begin + n]
            self.start[slot] = at
            at += int(self.capacity[slot])
        self.rows, self.used = rows, at


@njit(cache=True, nogil=True)
def _lay(
    rows: np.ndarray, start: np.ndarray, length: np.ndarray, slot: int, new: np.ndarray, horizon_ms: int
) -> None:
    begin, n = start[slot], length[slot]
    rows[begin + n : begin + n + new.shape[0]] = new
    n += new.shape[0]
    old = 0
    while old < n and rows[begin + old, 0] < horizon_ms:
        old += 1
    if old:
        rows[begin : begin + n - old] = rows[begin + old : begin + n].copy()
    length[slot] = n - old
