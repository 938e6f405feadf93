"""Visits from samples and from events, and their score against the truth."""

from __future__ import annotations

import numpy as np
import pytest

from slam_core.zones.visits import score_visits, visits_of, visits_of_events


def test_visits_are_the_runs_inside() -> None:
    t = np.arange(0, 10_000, 1_000)
    inside = np.array([0, 1, 1, 0, 0, 1, 1, 1, 0, 1], dtype=bool)
    assert visits_of(t, inside) == [(1_000, 3_000), (5_000, 8_000), (9_000, 9_000)]
    assert visits_of(t, np.zeros(10, dtype=bool)) == []
    with pytest.raises(ValueError, match="time order"):
        visits_of(np.array([2, 1]), np.array([True, True]))
    with pytest.raises(ValueError, match="one inside flag"):
        visits_of(t, inside[:3])


def test_events_tell_visits_and_an_open_one_ends_with_the_walk() -> None:
    kinds = ["enter", "dwell", "exit", "enter"]
    assert visits_of_events(kinds, [0, 5, 30, 40], 100) == [(0, 30), (40, 100)]
    assert visits_of_events(["exit", "enter", "enter", "exit"], [1, 2, 3, 4], 9) == [(2, 4)]


def test_long_visits_match_within_the_tolerance_and_false_transitions_are_counted() -> None:
    true = [(10_000, 40_000), (60_000, 65_000), (100_000, 130_000)]
    told = [(13_000, 42_000), (60_500, 64_000), (100_000, 120_000), (140_000, 141_000)]
    score = score_visits(true, told)
    assert score.true == 2  # the 5 s visit is too short to count
    assert score.told == 2  # so are the 3.5 s and 1 s told ones
    assert score.matched == 1  # the third ends 10 s early
    assert score.enter_delays_ms == (3_000,)
    assert score.f1 == pytest.approx(0.5)
    # told transitions the truth lacks: the exit at 120 s, and both ends of the visit at 140 s
    assert score.false_transitions == 3


def test_a_flickering_point_test_is_all_false_transitions() -> None:
    true = [(0, 60_000)]
    flicker = [(k * 2_000, k * 2_000 + 1_000) for k in range(30)]
    score = score_visits(true, flicker)
    assert score.matched == 0
    assert score.f1 == 0.0
    assert score.false_transitions == 2 * 30 - 2  # one entry near the true one and one exit near its exit
    assert score_visits([], []).f1 == 1.0
