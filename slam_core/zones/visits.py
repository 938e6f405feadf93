"""Visits to a zone, and how well the visits a tracker told match the true ones: the figures ``evaluate
--zones`` reports (visit F1, the delay of an entry, the transitions the truth does not have).

A visit is an interval (entered, left) in ms. The truth's come from where the user really was, sampled
(``visits_of``); the tracker's from its enter and exit events, or from a point test of its estimates (the
naive baseline, also ``visits_of``). Pure numerics.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from slam_core.zones.geometry import ZoneSet, points_inside

MIN_VISIT_MS = 10_000
"""A visit counts when it lasts at least this long (passing a shop front is no visit)."""
TOLERANCE_MS = 5_000
"""Two visits match when their entries and their exits are each this close."""


def visits_of(t_ms: np.ndarray, inside: np.ndarray) -> list[tuple[int, int]]:
    """The runs of ``inside`` in a time-ordered series of samples: each from its first sample inside to the
    first sample outside after it (or the last sample, when the series ends inside)."""
    t_ms = np.asarray(t_ms, dtype=np.int64)
    inside = np.asarray(inside, dtype=bool)
    if t_ms.shape != inside.shape:
        raise ValueError("one inside flag per sample")
    if t_ms.size > 1 and np.any(np.diff(t_ms) < 0):
        raise ValueError("samples must be in time order")
    out = []
    start = -1
    for k in range(t_ms.size):
        if inside[k] and start < 0:
            start = k
        elif not inside[k] and start >= 0:
            out.append((int(t_ms[start]), int(t_ms[k])))
            start = -1
    if start >= 0:
        out.append((int(t_ms[start]), int(t_ms[-1])))
    return out


def visits_of_events(kinds: list[str], t_ms: list[int], end_ms: int) -> list[tuple[int, int]]:
    """The visits told by one user's events in one zone, in time order ("enter", "exit"; dwells ignored); a
    visit still open at ``end_ms`` ends there."""
    out = []
    entered = None
    for kind, t in zip(kinds, t_ms, strict=True):
        if kind == "enter" and entered is None:
            entered = int(t)
        elif kind == "exit" and entered is not None:
            out.append((entered, int(t)))
            entered = None
    if entered is not None:
        out.append((entered, int(end_ms)))
    return out


@dataclass(frozen=True)
class VisitScore:
    matched: int
    """Visits of at least ``MIN_VISIT_MS`` on both sides whose entries and exits agree within the
    tolerance."""
    told: int
    """Visits the tracker told that lasted at least ``MIN_VISIT_MS``."""
    true: int
    """True visits of at least ``MIN_VISIT_MS``."""
    enter_delays_ms: tuple[int, ...]
    """For each match, how much later the tracker's entry was than the true one (negative: earlier)."""
    false_transitions: int
    """Entries and exits told (of visits of any length) left over once each true entry and exit (of any
    length) takes the nearest told one of its kind within the tolerance."""
    matched_entries: tuple[tuple[int, int], ...] = ()
    """For each match, the true entry's time and the told one's."""

    @property
    def f1(self) -> float:
        """2 matched / (told + true); 1.0 when neither side has a visit."""
        total = self.told + self.true
        return 1.0 if total == 0 else 2.0 * self.matched / total


def score_visits(true: list[tuple[int, int]], told: list[tuple[int, int]]) -> VisitScore:
    """One user's visits to one zone, told against true: long visits matched one to one in time order (each
    true visit with the earliest unmatched told visit within the tolerance at both ends), and every told
    transition checked against the true ones."""
    long_true = [v for v in true if v[1] - v[0] >= MIN_VISIT_MS]
    long_told = [v for v in told if v[1] - v[0] >= MIN_VISIT_MS]
    used = [False] * len(long_told)
    pairs = []
    for start, end in long_true:
        for k, (s, e) in enumerate(long_told):
            if not used[k] and abs(s - start) <= TOLERANCE_MS and abs(e - end) <= TOLERANCE_MS:
                used[k] = True
                pairs.append((start, s))
                break
    false = _unmatched([v[0] for v in told], [v[0] for v in true]) + _unmatched(
        [v[1] for v in told], [v[1] for v in true]
    )
    delays = tuple(s - start for start, s in pairs)
    return VisitScore(len(pairs), len(long_told), len(long_true), delays, false, tuple(pairs))


def _unmatched(told: list[int], true: list[int]) -> int:
    """How many of the told times are left once each true time takes the nearest told one within the
    tolerance (one each: a flicker at a true entry is one entry and several false ones)."""
    left = np.array(sorted(told), dtype=np.int64)
    taken = np.zeros(left.size, dtype=bool)
    for t in true:
        gap = np.where(taken, np.iinfo(np.int64).max, np.abs(left - t))
        if gap.size and gap.min() <= TOLERANCE_MS:
            taken[int(np.argmin(gap))] = True
    return int(left.size - taken.sum())


class ZoneTally:
    """What ``evaluate --zones`` counts over a run: for each user, at each scored estimate, whether its true
    position and its estimate (the naive point test) lie in each zone; and the entries and exits the
    tracker told. ``result`` scores both against the truth."""

    def __init__(self, zones: ZoneSet, ids: list[str]) -> None:
        self.zones = zones
        self.index = {zone_id: k for k, zone_id in enumerate(ids)}
        self._t: dict[str, list[int]] = {}
        self._points: dict[str, list[tuple[float, float, int, float, float, int]]] = {}
        """Per user, per sample: the true position and floor, the estimate and its floor."""
        self._told: dict[tuple[str, int], tuple[list[str], list[int]]] = {}
        self._decided: dict[tuple[str, int, int], int] = {}  # (user, zone, entry's stamp) -> when told

    def sample(
        self, user: str, t_ms: int, truth: np.ndarray, true_level: int, estimate: np.ndarray, level: int
    ) -> None:
        """A scored estimate of ``user`` at ``t_ms`` (its samples in time order); which zones hold it and the
        truth is found once, for all samples, by ``result``."""
        self._t.setdefault(user, []).append(int(t_ms))
        point = (
            float(truth[0]),
            float(truth[1]),
            int(true_level),
            float(estimate[0]),
            float(estimate[1]),
            level,
        )
        self._points.setdefault(user, []).append(point)

    def told(self, user: str, zone_id: str, kind: str, t_ms: int, told_ms: int | None = None) -> None:
        """An event the tracker told (dwells are no transitions): stamped ``t_ms``, decided at ``told_ms``
        (the stamp when not given)."""
        if kind in ("enter", "exit"):
            z = self.index[zone_id]
            kinds, times = self._told.setdefault((user, z), ([], []))
            kinds.append(kind)
            times.append(int(t_ms))
            if kind == "enter":
                self._decided[(user, z, int(t_ms))] = int(t_ms if told_ms is None else told_ms)

    def result(self) -> dict[str, Any]:
        """The tracker's figures (``visit_f1``, ``enter_delay_p50_s``: of the entries' stamps,
        ``false_transitions_per_hour``) and the same under ``naive``, with the counts behind them; and
        ``told_after_p50_s``: how long after the true entry the tracker was sure of a matched one."""
        told, naive = [], []
        hours = 0.0
        true_visits = 0
        told_after: list[int] = []
        for user, times in self._t.items():
            t = np.asarray(times, dtype=np.int64)
            hours += (int(t[-1]) - int(t[0])) / 3.6e6
            p = np.asarray(self._points[user], dtype=np.float64).reshape(t.size, 6)
            truth = points_inside(self.zones, p[:, 0], p[:, 1], p[:, 2].astype(np.int64))
            guess = points_inside(self.zones, p[:, 3], p[:, 4], p[:, 5].astype(np.int64))
            for z in range(len(self.zones)):
                true = visits_of(t, truth[:, z])
                true_visits += sum(v[1] - v[0] >= MIN_VISIT_MS for v in true)
                kinds, at = self._told.get((user, z), ([], []))
                score = score_visits(true, visits_of_events(kinds, at, int(t[-1])))
                told.append(score)
                told_after += [self._decided[(user, z, s)] - start for start, s in score.matched_entries]
                naive.append(score_visits(true, visits_of(t, guess[:, z])))
        return {
            **_figures(told, hours),
            "told_after_p50_s": float(np.median(told_after)) / 1000.0 if told_after else None,
            "naive": _figures(naive, hours),
            "zones": len(self.zones),
            "true_visits": int(true_visits),
            "user_hours": hours,
        }


def _figures(scores: list[VisitScore], hours: float) -> dict[str, Any]:
    matched = sum(s.matched for s in scores)
    total = sum(s.told + s.true for s in scores)
    delays = [d for s in scores for d in s.enter_delays_ms]
    false = sum(s.false_transitions for s in scores)
    return {
        "visit_f1": 1.0 if total == 0 else 2.0 * matched / total,
        "visits_matched": matched,
        "visits_told": sum(s.told for s in scores),
        "enter_delay_p50_s": float(np.median(delays)) / 1000.0 if delays else None,
        "false_transitions": int(false),
        "false_transitions_per_hour": false / hours if hours > 0 else None,
    }
