"""The tracker's floor stage: each user's belief over the building's floors (one probability a floor,
``slam_core.tracking.floors.Floors``), set by fixes and known places, moved by changes of height (a
barometer's or an SDK's rise, a lift or stairs without one), and weighed by the floors' crowd fingerprint
maps, near the user's estimate or, before it has one, anywhere on each floor.

``FloorStage`` owns the beliefs, by user name (a phone not yet started has one: its cold start picks its
floor first), and the building's ``Floors``. The tracker tells it when a user joins or leaves and moves the
filters of the users whose believed floor changes (``BuildingTracker._follow_floors``). Pure numerics."""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable, Iterable

import numpy as np

from slam_core.tracking.floors import FloorParams, Floors

FloorEvidence = Callable[[tuple[int, ...], list[str], np.ndarray], np.ndarray]
"""The floors' log-likelihoods of a scan (its BSSIDs and RSS), in the order of the floors' levels."""


class FloorStage:
    def __init__(self, params: FloorParams) -> None:
        self.params = params
        self.floors = Floors(params)
        # a flat array of doubles a user: the collector does not walk it and a snapshot writes it as one block
        self._beliefs: dict[str, array[float]] = {}

    # ------------------------------------------------------------------ the building's floors
    @property
    def levels(self) -> tuple[int, ...]:
        return self.floors.levels

    @property
    def single(self) -> bool:
        return self.floors.single

    def index(self, level: int) -> int:
        """The floor's index among the levels (ValueError naming the building's floors for another)."""
        return self.floors.index(level)

    def set_levels(self, levels: tuple[int, ...], elevations_m: tuple[float, ...] | None = None) -> None:
        """The building's floors (and their heights where known; NaN: from the storey height). A user's belief
        keeps its share on the floors that stay; a floor taken away takes its users' share with it (a user
        left with nothing starts over, unsure among all floors)."""
        old = self.floors
        new = Floors(self.params, tuple(levels), elevations_m)
        new.adopt(old)
        if new.levels != old.levels:
            for user, belief in self._beliefs.items():
                p = np.zeros(len(new.levels))
                for level, q in zip(old.levels, belief, strict=True):
                    if level in new.levels:
                        p[new.index(level)] = q
                self._beliefs[user] = array("d", (p / p.sum() if p.sum() > 0 else new.uniform()).tolist())
        self.floors = new

    # ------------------------------------------------------------------ the users' beliefs
    def join(self, user: str) -> None:
        """A new user, unsure among all floors."""
        self._beliefs[user] = array("d", self.floors.uniform().tolist())

    def leave(self, user: str) -> None:
        self._beliefs.pop(user, None)

    def belief(self, user: str) -> np.ndarray:
        return np.asarray(self._beliefs[user])

    def believed(self, user: str) -> tuple[int, float]:
        """The floor the user is believed on and the belief's probability."""
        return self.floors.believed(np.asarray(self._beliefs[user]))

    def believed_of(self, users: Iterable[str]) -> list[tuple[int, float]]:
        floors, beliefs = self.floors, self._beliefs
        return [floors.believed(np.asarray(beliefs[u])) for u in users]

    def start(self, user: str, level: int) -> None:
        """A fix or a known place on ``level``: the user is there."""
        self._beliefs[user] = array("d", self.floors.start(level).tolist())

    def rise(self, user: str, rise_m: float) -> None:
        """The user's height changed by ``rise_m``: its belief moves by storeys, and the crowd measures the
        storeys from the move (``Floors.learn``)."""
        before = np.asarray(self._beliefs[user])
        after = self.floors.rise(before, rise_m)
        self.floors.learn(before, after, rise_m)
        self._beliefs[user] = array("d", after.tolist())

    def maybe_changed(self, user: str) -> None:
        """A phone without a barometer at stairs, a lift or an escalator: maybe on another floor now."""
        self._beliefs[user] = array("d", self.floors.maybe_changed(np.asarray(self._beliefs[user])).tolist())

    def weigh_near(self, user: str, believed_level: int, log_likelihood: np.ndarray) -> bool:
        """The floors' evidence of a tracked user's latest scan near its estimate: weighs its belief, unless
        the believed floor's crowd never walked there (no evidence either way). Whether it was weighed."""
        if not math.isfinite(log_likelihood[self.floors.index(believed_level)]):
            return False
        weighed = self.floors.weigh(np.asarray(self._beliefs[user]), log_likelihood)
        self._beliefs[user] = array("d", weighed.tolist())
        return True

    def weigh_scans(
        self, user: str, scans: Iterable[tuple[list[str], np.ndarray]], evidence: FloorEvidence
    ) -> None:
        """A phone not started yet: each of its scans, in time order, weighs its belief by every floor's map
        anywhere on the floor."""
        belief = np.asarray(self._beliefs[user])
        for bssids, rss in scans:
            belief = self.floors.weigh(belief, evidence(self.floors.levels, bssids, rss))
        self._beliefs[user] = array("d", belief.tolist())
