"""Which floor each user is on: a probability per floor of the building, per user (beyond both papers, which
track one floor; SignalSLAM names the barometer with stairs and lift detection as the way to multi-floor).

The floor is a discrete state beside each user's particle cloud, not a dimension of its particles. The
cloud's (x, y) is the same place on every floor (stairs and lifts are vertical), and what the floor decides
for the filter is which plan weighs the steps, which anchors the detections join, which fingerprints place the
scans and which users can meet: all of them per user, so a per-particle floor would cost a plan lookup and a
map per particle for evidence that is per user. A user's belief is a small vector over the building's levels,
updated as a hidden Markov model:

- **a start** from a fix, tag or known anchor that names the floor: all but ``start_doubt`` on it;
- **a change of height** (the barometer's settled change, or a lift ride's rise from the accelerometer): the
  belief moves by the storeys whose height difference explains the rise, each level pair weighed by
  N(rise; elevation_j - elevation_i, sigma^2), plus ``false_change`` for a change that was not one; the
  heights are the operator's, else the ones the crowd's confident one-storey changes measured;
- **a way between floors without its rise** (stairs, a lift or an escalator from a phone without a
  barometer): ``unmeasured_change`` of the belief moves to the adjacent floors, for the radio to settle;
- **radio evidence**: the per-floor likelihoods of a scan (``FingerprintStage.floor_evidence``), after a
  ``switch_rate`` transition to the neighbouring floors, so that a belief that was wrong (a missed ride, a
  wrong fix) is drawn back by the radio within a few scans rather than never.

The believed floor is the most probable one, and its probability is what the estimate calls the floor's
confidence. Pure numerics.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FloorParams:
    storey_m: float = 4.5
    """Height between floors where the operator gave no elevations: shopping malls and offices have 3.5-5.5 m
    storeys; the rise model's sigma covers the rest."""
    rise_sigma_m: float = 1.2
    """A barometer's settled change is good to ~0.3 m; storeys of one building differ by a metre or more."""
    rise_sigma_share: float = 0.1
    """... plus this share of the rise (a long ride's pressure drifts with it)."""
    false_change: float = 0.02
    """Probability that a detected change of height was no change of floor (a ramp, a door's draught)."""
    start_doubt: float = 0.001
    """Share of a start's belief spread over the other floors (a fix that names the wrong floor can be
    recovered from)."""
    switch_rate: float = 0.003
    """Probability, per radio observation, of a change of floor that no sensor saw (a phone without a
    barometer on the stairs) to each adjacent floor, before the radio weighs the belief."""
    radio_weight: float = 0.5
    """Radio log-likelihoods are tempered by this: consecutive scans of one place are not independent."""
    radio_sigma_db: float = 5.0
    """A scan's union distance to a reference of the same place (``FingerprintStage.floor_evidence``)."""
    radio_radius_m: float = 10.0
    """A tracked user's scan is compared with each floor's references within this of its estimate."""
    radio_place_sigma_m: float = 4.0
    """... each weighed by its distance from the estimate with this sigma (a fingerprint cell)."""
    unmeasured_change: float = 0.3
    """Stairs, a lift or an escalator detected by a phone without a barometer (no rise): the share of the
    belief moved to the adjacent floors, for the radio to confirm or take back (the user may only have
    passed it)."""
    escalator_incline_deg: float = 30.0
    """An escalator ride carries the user ``rise / tan(incline)`` without a step (EN 115: 30 deg, 35 deg for
    rises under 6 m)."""
    storey_learning_min: int = 3
    """A gap between two levels is the crowd's measured one once this many confident one-storey changes
    measured it (``Floors.learn``); until then, the storey height (from other gaps, or the default)."""
    storey_memory: int = 100
    """... a running mean over about this many of the latest."""
    join_confidence: float = 0.95
    """A user's scans join its floor's fingerprint map only when the belief in that floor is this high."""

    def __post_init__(self) -> None:
        if not (
            self.storey_m > 0
            and self.rise_sigma_m > 0
            and self.rise_sigma_share >= 0
            and 0 <= self.false_change < 1
            and 0 <= self.start_doubt < 1
            and 0 <= self.switch_rate <= 0.25
            and 0 < self.radio_weight <= 1
            and self.radio_sigma_db > 0
            and self.radio_radius_m > 0
            and self.radio_place_sigma_m > 0
            and 0 < self.join_confidence <= 1
            and 0 <= self.unmeasured_change < 1
            and 0 < self.escalator_incline_deg < 90
            and self.storey_learning_min >= 1
            and self.storey_memory >= self.storey_learning_min
        ):
            raise ValueError(
                "floor parameters: storey_m, rise_sigma_m, radio_sigma_db, radio_radius_m must be positive, "
                "radio_weight and join_confidence in (0, 1], false_change, start_doubt and unmeasured_change "
                "in [0, 1), switch_rate in [0, 0.25], escalator_incline_deg in (0, 90), "
                "1 <= storey_learning_min <= storey_memory"
            )


NO_CHANGE_SPAN_M = 20.0
"""A measured rise that was no change of floor is taken as anything within this, up or down."""


class Floors:
    """The building's levels and their heights, and the belief updates over them. A belief is a float array,
    one probability per level in ``levels``' order."""

    def __init__(
        self,
        params: FloorParams,
        levels: tuple[int, ...] = (0,),
        elevations_m: tuple[float, ...] | None = None,
    ) -> None:
        if not levels or len(set(levels)) != len(levels):
            raise ValueError("a building has at least one level, each once")
        order = np.argsort(levels)
        self.params = params
        self.levels = tuple(int(levels[i]) for i in order)
        given = (
            np.full(len(levels), math.nan)
            if elevations_m is None
            else np.asarray([elevations_m[i] for i in order], dtype=float)
        )
        if given.shape != (len(levels),):
            raise ValueError("one elevation (or NaN) per level")
        self._given = given
        n = len(self.levels)
        self._gap_sum = np.zeros(max(n - 1, 0))  # learned: the crowd's measured rises between adjacent levels
        self._gap_n = np.zeros(max(n - 1, 0))
        self.heights_m = self._heights()
        self._index = {lv: i for i, lv in enumerate(self.levels)}
        # undetected changes: ``switch_rate`` to each floor just above and below, the rest stays. Symmetric,
        # so evidence that tells no floor apart spreads a belief towards uniform (the filter hesitates) and
        # never towards the middle floors
        adj = np.eye(n, k=1) + np.eye(n, k=-1)
        self._switch = np.eye(n) - params.switch_rate * (np.diag(adj.sum(axis=1)) - adj)
        # a way between floors seen without its rise: ``unmeasured_change`` to the neighbours, split
        neighbours = adj / np.maximum(adj.sum(axis=1, keepdims=True), 1.0)
        self._unmeasured = (1.0 - params.unmeasured_change) * np.eye(
            n
        ) + params.unmeasured_change * neighbours

    def _heights(self) -> np.ndarray:
        """Each level's height: the operator's where given; else from the nearest given level (or from level
        0 at 0 m: only differences matter) by the gaps between, each the crowd's learned gap where it has
        ``storey_learning_min`` measurements, else the storeys it spans times the storey height (the crowd's
        mean per storey where it measured any gap, else ``storey_m``)."""
        prm = self.params
        levels = np.asarray(self.levels, dtype=float)
        spans = np.diff(levels)
        learned = self._gap_n >= prm.storey_learning_min
        storey = prm.storey_m
        if learned.any():
            storey = float(np.sum(self._gap_sum[learned]) / np.sum(self._gap_n[learned] * spans[learned]))
        gaps = np.where(learned, self._gap_sum / np.maximum(self._gap_n, 1.0), spans * storey)
        heights = np.concatenate([[levels[0] * storey], levels[0] * storey + np.cumsum(gaps)])
        known = np.flatnonzero(np.isfinite(self._given))
        if known.size:
            for i in range(len(self.levels)):
                j = int(known[np.argmin(np.abs(known - i))])
                heights[i] = self._given[j] + heights[i] - heights[j]
        return heights

    def learn(self, before: np.ndarray, after: np.ndarray, rise_m: float) -> bool:
        """A change of height that took a user, sure of its floor before and after, one level up or down
        measures the gap between those two levels (beyond both papers: storeys differ, and operators seldom
        enter elevations). A rise far from the gap as known (under half or over twice: a missed or extra
        storey) is not taken. Returns whether it was."""
        prm = self.params
        if self.single or not math.isfinite(rise_m):
            return False
        i, p_before = int(np.argmax(before)), float(np.max(before))
        j, p_after = int(np.argmax(after)), float(np.max(after))
        if min(p_before, p_after) < prm.join_confidence or abs(i - j) != 1 or (j > i) != (rise_m > 0):
            return False
        k = min(i, j)
        if np.isfinite(self._given[k]) and np.isfinite(self._given[k + 1]):
            return False  # the operator gave both: nothing to learn
        known = abs(self.heights_m[k + 1] - self.heights_m[k])
        if not 0.5 * known <= abs(rise_m) <= 2.0 * known:
            return False
        if self._gap_n[k] >= prm.storey_memory:  # a running mean over the latest measurements
            self._gap_sum[k] *= (prm.storey_memory - 1) / prm.storey_memory
            self._gap_n[k] = prm.storey_memory - 1
        self._gap_sum[k] += abs(rise_m)
        self._gap_n[k] += 1
        self.heights_m = self._heights()
        return True

    def adopt(self, old: Floors) -> None:
        """Keep what ``old`` learned of the gaps between the pairs of adjacent levels both have."""
        pairs = {(a, b): k for k, (a, b) in enumerate(itertools.pairwise(old.levels))}
        for k, pair in enumerate(itertools.pairwise(self.levels)):
            if pair in pairs:
                self._gap_sum[k] = old._gap_sum[pairs[pair]]
                self._gap_n[k] = old._gap_n[pairs[pair]]
        self.heights_m = self._heights()

    @property
    def single(self) -> bool:
        return len(self.levels) == 1

    def index(self, level: int) -> int:
        """The position of a level in a belief; ValueError naming the building's levels for an unknown one."""
        i = self._index.get(int(level))
        if i is None:
            raise ValueError(f"no floor {level}; the building's floors: {', '.join(map(str, self.levels))}")
        return i

    def start(self, level: int) -> np.ndarray:
        """A belief that starts on ``level``."""
        n = len(self.levels)
        if n == 1:
            return np.ones(1)
        p = np.full(n, self.params.start_doubt / (n - 1))
        p[self.index(level)] = 1.0 - self.params.start_doubt
        return p

    def uniform(self) -> np.ndarray:
        return np.full(len(self.levels), 1.0 / len(self.levels))

    def rise(self, p: np.ndarray, rise_m: float) -> np.ndarray:
        """The belief after a settled change of height of ``rise_m`` (up positive): from each level i, a
        change to level j is weighed (1 - f) / (n - 1) x N(rise; dz_ij, sigma^2), and no change at all (a
        ramp, a draught, a detector's mistake) f x U(rise) over +-``NO_CHANGE_SPAN_M``, f ``false_change``.
        So the top floor going up stays where it is, rather than being sent to the one floor below."""
        if self.single or not math.isfinite(rise_m):
            return p
        prm = self.params
        n = len(self.levels)
        sigma = prm.rise_sigma_m + prm.rise_sigma_share * abs(rise_m)
        diff = self.heights_m[None, :] - self.heights_m[:, None]  # [from, to]
        like = (1.0 - prm.false_change) / (n - 1) * np.exp(-0.5 * ((diff - rise_m) / sigma) ** 2)
        like /= math.sqrt(2.0 * math.pi) * sigma
        np.fill_diagonal(like, prm.false_change / (2.0 * NO_CHANGE_SPAN_M))
        trans = like / like.sum(axis=1, keepdims=True)
        return _normalised(p @ trans)

    def maybe_changed(self, p: np.ndarray) -> np.ndarray:
        """The belief after a way between floors was detected without its rise: ``unmeasured_change`` of each
        level's share moves to its neighbours (split between them), the rest stays."""
        if self.single:
            return p
        return _normalised(p @ self._unmeasured)

    def weigh(self, p: np.ndarray, log_likelihood: np.ndarray) -> np.ndarray:
        """The belief after radio evidence: ``log_likelihood`` per level (NaN where a floor knows nothing: it
        counts as the worst of those that know), after the chance of an unseen change. Evidence from fewer
        than two floors compares nothing and changes nothing."""
        if self.single:
            return p
        ll = np.asarray(log_likelihood, dtype=float)
        if ll.shape != p.shape:
            raise ValueError("one log-likelihood per level")
        known = np.isfinite(ll)
        if known.sum() < 2:  # one floor alone cannot be compared: no evidence
            return p
        prior = p @ self._switch
        ll = np.where(known, ll, ll[known].min())  # an unknown level: no better than the worst known one
        w = self.params.radio_weight * (ll - ll.max())
        return _normalised(prior * np.exp(w))

    def believed(self, p: np.ndarray) -> tuple[int, float]:
        """The most probable level and its probability."""
        i = int(np.argmax(p))
        return self.levels[i], float(p[i])


def _normalised(p: np.ndarray) -> np.ndarray:
    total = float(p.sum())
    if not (total > 0 and math.isfinite(total)):
        raise ValueError("a floor belief lost all its mass")
    out: np.ndarray = p / total
    return out
