"""Each tracked user's dead-reckoned trail: the path its steps laid since it started, kept ``TRAIL_MS``
back, for placing readings in time (``slam_core.tracking.carry``)."""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass, field

import numpy as np

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
    trail: array[float] = field(default_factory=lambda: array("d"))
    """Recent steps, four numbers each: time (ms, exact in a double), displacement x and y after it, distance
    walked after it. A flat array of doubles: the garbage collector does not walk it and a snapshot writes
    it as one block, where a list of small tuples would be thousands of objects a user for both."""
    floor_belief: array[float] = field(default_factory=lambda: array("d", [1.0]))
    """The belief over the building's floors, one probability per level (``slam_core.tracking.floors``)."""

    # A user travels in a snapshot as one flat tuple, its fields in declaration order and its 2-vectors as
    # plain floats: thousands of tiny arrays, or of dicts naming every field, pickle slowly one by one, in
    # the building's thread.

    def __getstate__(self) -> tuple[object, ...]:
        d, o, g = self.displacement, self.origin, self.gyro_displacement
        sg, sl = self.since_gyro, self.since_laid
        return (
            self.number, self.slot, self.last_t_ms, self.heading, self.walked, self.heading_offset,
            self.trail, float(d[0]), float(d[1]), float(o[0]), float(o[1]), float(g[0]), float(g[1]),
            float(sg[0]), float(sg[1]), float(sl[0]), float(sl[1]), self.placed, self.floor_belief,
        )  # fmt: skip

    def __setstate__(self, state: tuple[object, ...]) -> None:
        (
            self.number, self.slot, self.last_t_ms, self.heading, self.walked, self.heading_offset,
            self.trail, dx, dy, ox, oy, gx, gy, sgx, sgy, slx, sly, self.placed, self.floor_belief,
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

    def recent_velocity(self) -> tuple[float, float]:
        """Dead-reckoned velocity (m per ms): the displacement from the last step at least
        ``VELOCITY_WINDOW_MS`` before the latest one (the oldest kept when the trail is shorter) to the
        latest, over that window, capped at ``MAX_SPEED_M_PER_MS``; how ``SlotColumns.extrapolated`` guesses
        a user not heard yet."""
        trail = self.trail
        if not trail:
            return 0.0, 0.0
        horizon = trail[-4] - VELOCITY_WINDOW_MS
        i = len(trail) - 4
        while i > 0 and trail[i] > horizon:
            i -= 4
        vx = (trail[-3] - trail[i + 1]) / VELOCITY_WINDOW_MS
        vy = (trail[-2] - trail[i + 2]) / VELOCITY_WINDOW_MS
        return cap_speed(vx, vy)

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
