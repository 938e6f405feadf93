"""A tracker call's rounds: the users' events in time order, cut into rounds of one tracker call each (the
first step, detection or fix of every user, then the next, ...), and a round's steps laid on the trails."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam_core.tracking.trails import Trails, UserTrack


@dataclass
class Round:
    users: list[str] = field(default_factory=list)
    step_len: list[np.ndarray] = field(default_factory=list)
    step_head: list[np.ndarray] = field(default_factory=list)
    det_users: list[str] = field(default_factory=list)
    det_types: list[int] = field(default_factory=list)
    det_t: list[int] = field(default_factory=list)
    det_signature: list[str] = field(default_factory=list)
    det_rise: list[float] = field(default_factory=list)  # a change of floor's rise, NaN for the others
    fix_users: list[str] = field(default_factory=list)
    fix_xy: list[np.ndarray] = field(default_factory=list)
    fix_sigma: list[float] = field(default_factory=list)
    fix_level: list[int] = field(default_factory=list)

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


def lay_steps(
    users: list[UserTrack], rnd: Round, lengths: np.ndarray, headings: np.ndarray, trails: Trails
) -> None:
    """Every user's steps of a round (``lengths`` and ``headings``: the round's, concatenated) on its
    dead-reckoned path and its trail in ``trails``: the trigonometry of all users' steps in one array pass
    (a Python pass per user had cost more than the engine's motion update)."""
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
            trails,
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
