"""Visits to a zone, and how well the visits a tracker told match the true ones: the figures ``evaluate
--zones`` reports (visit F1, the delay of an entry, the transitions the truth does not have).

A visit is an interval (entered, left) in ms. The truth's come from where the user really was, sampled
(``visits_of``); the tracker's from its enter and exit events, or from a point test of its estimates (the
naive baseline, also ``visits_of``). Pure numerics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    """For each match, how much later the tracker told the entry than it happened (negative: earlier)."""
    false_transitions: int
    """Entries and exits told (of visits of any length) left over once each true entry and exit (of any
    length) takes the nearest told one of its kind within the tolerance."""

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
    delays = []
    for start, end in long_true:
        for k, (s, e) in enumerate(long_told):
            if not used[k] and abs(s - start) <= TOLERANCE_MS and abs(e - end) <= TOLERANCE_MS:
                used[k] = True
                delays.append(s - start)
                break
    false = _unmatched([v[0] for v in told], [v[0] for v in true]) + _unmatched(
        [v[1] for v in told], [v[1] for v in true]
    )
    return VisitScore(len(delays), len(long_told), len(long_true), tuple(delays), false)


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
