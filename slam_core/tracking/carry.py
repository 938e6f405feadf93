"""Readings carried in time on the tracker's users: back along a user's own steps to now (``carried_since``,
over many users' trails in one search), or, for a user whose phone has not reported up to a reading yet,
guessed ahead at its recent velocity (``SlotColumns``). Pure numerics."""

from __future__ import annotations

import numpy as np
from numba import njit

from slam_core.tracking.trails import TRAIL_MS, Trails, UserTrack

CARRY_DRIFT = 0.1
"""Dead reckoning's error per metre walked (PDR drifts ~10-13 % of the distance on the real walks): the
standard deviation given to an observation carried from its time to now along the user's own steps."""


def carry_variance(walked_m: np.ndarray | float) -> np.ndarray:
    """Variance (m^2) of a position carried over ``walked_m`` metres of the user's own dead reckoning."""
    return np.square(CARRY_DRIFT * np.asarray(walked_m, dtype=np.float64))


def trail_lookup(
    trails: Trails,
    slots: np.ndarray,
    t_ms: np.ndarray,
    last_t_ms: np.ndarray,
    displacement: np.ndarray,
    walked: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Dead-reckoned displacement and distance walked of the user in ``slots[i]`` at ``t_ms[i]`` (its last
    step then; the oldest kept when older than its trail; where it is now, ``displacement[i]`` and
    ``walked[i]``, when it has no trail, or when the time is before its trail and not before its last event
    ``last_t_ms[i]``), for every i: (n, 2) displacements and (n,) distances walked. One compiled search over
    all the users' trails, not a pass per user: a busy call carries readings of hundreds of users."""
    out_xy = np.array(displacement, dtype=np.float64).reshape(-1, 2)
    out_walked = np.array(walked, dtype=np.float64)
    _lookup(
        trails.rows, trails.start, trails.length, np.asarray(slots, dtype=np.int64),
        np.asarray(t_ms, dtype=np.int64), np.asarray(last_t_ms, dtype=np.int64), out_xy, out_walked,
    )  # fmt: skip
    return out_xy, out_walked


def carried_since(
    trails: Trails, slots: np.ndarray, last_t_ms: np.ndarray, t_ms: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From ``t_ms[i]`` to now along the steps of the user in ``slots[i]`` (its last event ``last_t_ms[i]``):
    (n, 2) displacement, (n,) the distance walked (``carry_variance`` gives the carry's variance), and (n,)
    whether the time can be placed at all (the user's trail reaches back to it). A time not before the
    user's last event, or a user without a trail, is carried nowhere."""
    t = np.asarray(t_ms, dtype=np.int64)
    last = np.asarray(last_t_ms, dtype=np.int64)
    shift, walked = np.zeros((t.size, 2)), np.zeros(t.size)
    _carry(
        trails.rows, trails.start, trails.length, np.asarray(slots, dtype=np.int64), t, last, shift, walked
    )
    return shift, walked, t >= last - TRAIL_MS


@njit(cache=True, nogil=True)
def _row_at(rows: np.ndarray, begin: int, n: int, t: np.int64, last: np.int64) -> int:
    """The row of a trail (``n`` rows from ``begin``) for a time: its last step at or before it, else its
    oldest while the time is before the user's last event; -1: none (the user is where it is now)."""
    if n == 0:
        return -1
    lo, hi = 0, n
    while lo < hi:  # the steps at or before t (exact integer ms)
        mid = (lo + hi) // 2
        if np.int64(rows[begin + mid, 0]) <= t:
            lo = mid + 1
        else:
            hi = mid
    if lo > 0:
        return begin + lo - 1
    return begin if t < last else -1


@njit(cache=True, nogil=True)
def _lookup(
    rows: np.ndarray,
    start: np.ndarray,
    length: np.ndarray,
    slots: np.ndarray,
    t: np.ndarray,
    last: np.ndarray,
    out_xy: np.ndarray,
    out_walked: np.ndarray,
) -> None:
    for i in range(slots.size):
        s = slots[i]
        r = _row_at(rows, start[s], length[s], t[i], last[i])
        if r >= 0:
            out_xy[i, 0], out_xy[i, 1], out_walked[i] = rows[r, 1], rows[r, 2], rows[r, 3]


@njit(cache=True, nogil=True)
def _carry(
    rows: np.ndarray,
    start: np.ndarray,
    length: np.ndarray,
    slots: np.ndarray,
    t: np.ndarray,
    last: np.ndarray,
    shift: np.ndarray,
    walked: np.ndarray,
) -> None:
    for i in range(slots.size):
        if t[i] >= last[i]:
            continue  # nothing walked since
        s = slots[i]
        n = length[s]
        r = _row_at(rows, start[s], n, t[i], last[i])
        if r < 0:
            continue
        now = start[s] + n - 1  # where the user is now: its last step
        shift[i, 0] = rows[now, 1] - rows[r, 1]
        shift[i, 1] = rows[now, 2] - rows[r, 2]
        walked[i] = rows[now, 3] - rows[r, 3]


GUESS_SIGMA_FRACTION = 0.5
"""A user guessed ahead may have stopped or turned: the guess's sigma is half its length."""


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

    def update(self, tracks: list[UserTrack], heard_t_ms: list[int], trails: Trails) -> None:
        """After a call's events: its tracked users as they are now (their steps in ``trails``), each heard
        up to ``heard_t_ms`` (its batch's latest time of anything)."""
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
            last_step = trails.last_step_ms(u.slot)
            walking = last_step is not None and heard - last_step <= STANDING_MS
            self.velocity[u.slot] = trails.recent_velocity(u.slot) if walking else (0.0, 0.0)

    def reach(self, slots: np.ndarray, t_ms: np.ndarray) -> np.ndarray:
        """A bound on how far each user walked after ``t_ms`` (at least that far): 0 when it has not reported
        steps past it, its latest batch's walk when the time is within that batch, infinity (unknown) when
        older."""
        result = np.empty(len(slots))
        _reach(
            np.asarray(slots, dtype=np.int64), np.asarray(t_ms, dtype=np.int64), self.walked,
            self.start_walked, self.start_t_ms, self.last_t_ms, result,
        )  # fmt: skip
        return result

    def extrapolated(self, slots: np.ndarray, t_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where each user has gone from its phone's last report to ``t_ms``, a time it has not reported
        yet, at its recent velocity (``Trails.recent_velocity``; zero for a user standing at its last
        report): (n, 2) displacement (zero when the time has been reported); (n,) the variance of that guess
        (its sigma ``GUESS_SIGMA_FRACTION`` of its length); and (n,) whether it is guessed at all (not after
        ``MAX_EXTRAPOLATION_MS`` of silence). One compiled pass over the readings."""
        n = len(slots)
        ahead, variance, heard = np.empty((n, 2)), np.empty(n), np.empty(n, dtype=np.bool_)
        _extrapolated(
            np.asarray(slots, dtype=np.int64), np.asarray(t_ms, dtype=np.int64), self.heard_t_ms,
            self.velocity, GUESS_SIGMA_FRACTION**2, MAX_EXTRAPOLATION_MS, ahead, variance, heard,
        )  # fmt: skip
        return ahead, variance, heard


@njit(cache=True, nogil=True)
def _reach(
    slots: np.ndarray,
    t: np.ndarray,
    walked: np.ndarray,
    start_walked: np.ndarray,
    start_t_ms: np.ndarray,
    last_t_ms: np.ndarray,
    out: np.ndarray,
) -> None:
    for i in range(slots.size):
        s = slots[i]
        if t[i] >= last_t_ms[s]:
            out[i] = 0.0
        elif t[i] >= start_t_ms[s]:
            out[i] = walked[s] - start_walked[s]
        else:
            out[i] = np.inf


@njit(cache=True, nogil=True)
def _extrapolated(
    slots: np.ndarray,
    t: np.ndarray,
    heard_t_ms: np.ndarray,
    velocity: np.ndarray,
    fraction2: float,
    max_silence_ms: int,
    ahead: np.ndarray,
    variance: np.ndarray,
    heard: np.ndarray,
) -> None:
    """``SlotColumns.extrapolated``, a reading at a time: the guess ``ahead`` and its variance,
    ``fraction2 * |ahead|^2`` (m^2)."""
    for i in range(slots.size):
        s = slots[i]
        silence = t[i] - heard_t_ms[s]
        dt = float(max(silence, 0))
        ax, ay = velocity[s, 0] * dt, velocity[s, 1] * dt
        ahead[i, 0], ahead[i, 1] = ax, ay
        variance[i] = fraction2 * (ax * ax + ay * ay)
        heard[i] = silence <= max_silence_ms
