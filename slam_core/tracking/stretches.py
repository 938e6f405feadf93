"""Straight stretches of each user's walk, as the phone measured its steps: what the floor plan's grid is
compared with (``DynamicSlam.observe_heading_axis``).

A stretch grows step by step while every step points within ``turn_rad`` of the stretch's direction so far
(the length-weighted mean of its steps' directions); a step further off is a turn and starts a new stretch.
Once a stretch is ``length_m`` long it is reported and the next one starts: a long corridor gives one
observation every ``length_m``, so its weight grows with the distance walked along it, not with the step
rate.
"""

from __future__ import annotations

import math

import numpy as np


class StraightStretches:
    def __init__(self, length_m: float, turn_rad: float) -> None:
        if not (length_m > 0 and turn_rad > 0):
            raise ValueError("a stretch's length and turn must be > 0")
        self.length_m = length_m
        self.turn_rad = turn_rad
        # Per user, its open stretch: the sum of its steps as vectors (x, y) and its length.
        self._open: dict[str, tuple[float, float, float]] = {}

    def add(self, user: str, lengths: np.ndarray, headings: np.ndarray) -> list[float]:
        """The user's next steps (metres; rad, counter-clockwise from east); returns the direction of each
        stretch they complete, in order."""
        sx, sy, walked = self._open.get(user, (0.0, 0.0, 0.0))
        done = []
        for length, heading in zip(lengths.tolist(), headings.tolist(), strict=True):
            if length <= 0.0:
                continue
            dx, dy = length * math.cos(heading), length * math.sin(heading)
            if walked > 0.0:
                turn = math.atan2(sx * dy - sy * dx, sx * dx + sy * dy)  # from the stretch's direction
                if abs(turn) > self.turn_rad:
                    sx = sy = walked = 0.0
            sx, sy, walked = sx + dx, sy + dy, walked + length
            if walked >= self.length_m:
                done.append(math.atan2(sy, sx))
                sx = sy = walked = 0.0
        self._open[user] = (sx, sy, walked)
        return done

    def forget(self, user: str) -> None:
        """The user's walk was interrupted (a removal, a restarted timeline): its open stretch is dropped."""
        self._open.pop(user, None)

    def __len__(self) -> int:
        return len(self._open)
