"""Visits from samples and from events, and their score against the truth."""

from __future__ import annotations

import numpy as np
import pytest

from slam_core.zones.geometry import points_inside, zone_set
from slam_core.zones.visits import ZoneTally, score_visits, visits_of, visits_of_events


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


def test_a_tally_scores_told_visits_and_the_point_test_against_the_truth() -> None:
    """A user walks east through a zone (x 0..20 m) at 1 m/s for 60 s: truly inside from 10 s to 30 s. The
    tracker tells one visit a second late at both ends; its estimate is 0.3 m north of the truth, so the
    point test tells the true visit. Then one estimate thrown 11 m back splits the point test's visit."""
    zones = zone_set([np.array([[0.0, -5.0], [20.0, -5.0], [20.0, 5.0], [0.0, 5.0]])], [0])
    tally = ZoneTally(zones, ["shop"])
    for s in range(61):
        truth = np.array([s - 10.0, 0.0])
        estimate = truth + np.array([0.0, 0.3])
        tally.sample("u", s * 1000, truth, 0, estimate, 0)
        tally.sample("v", s * 1000, truth, 1, estimate, 1)  # another floor: the zone is not there
    tally.told("u", "shop", "enter", 11_000, 12_500)
    tally.told("u", "shop", "dwell", 12_000)
    tally.told("u", "shop", "exit", 31_000)
    result = tally.result()
    assert result["visit_f1"] == 1.0
    assert result["visits_matched"] == 1
    assert result["enter_delay_p50_s"] == 1.0
    assert result["told_after_p50_s"] == 2.5
    assert result["false_transitions"] == 0
    assert result["true_visits"] == 1
    assert result["user_hours"] == 2 * 60 / 3600
    naive = result["naive"]
    assert naive["visit_f1"] == 1.0
    assert naive["false_transitions"] == 0
    tally2 = ZoneTally(zones, ["shop"])
    for s in range(61):
        truth = np.array([s - 10.0, 0.0])
        error = -11.0 if s == 20 else 0.0  # one estimate thrown back before the zone
        tally2.sample("u", s * 1000, truth, 0, truth + np.array([error, 0.0]), 0)
    naive = tally2.result()["naive"]
    assert naive["false_transitions"] == 2
    assert naive["false_transitions_per_hour"] == 2 / (60 / 3600)
    assert naive["visit_f1"] == 0.0  # 10..20 and 21..30 s: neither ends within 5 s of the true exit
    assert tally2.result()["visits_told"] == 0
    assert tally2.result()["visit_f1"] == 0.0  # nothing told of a true visit


def test_points_inside_agree_with_the_particle_share() -> None:
    ring = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [2.0, 1.0], [0.0, 4.0]])  # a notched square
    zones = zone_set([ring, ring + 10.0], [0, 1])
    x = np.array([1.0, 2.0, 2.0, 12.0, 12.0, np.nan])
    y = np.array([1.0, 3.0, 0.5, 10.5, 10.5, 1.0])
    level = np.array([0, 0, 0, 1, 0, 0])
    inside = points_inside(zones, x, y, level)
    assert inside.tolist() == [
        [True, False],
        [False, False],  # in the notch
        [True, False],
        [False, True],
        [False, False],  # the other floor
        [False, False],  # no estimate
    ]
