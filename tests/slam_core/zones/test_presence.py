"""Entries, exits and dwells decided with the probability inside, with hysteresis."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from slam_core.zones.presence import DWELL, ENTER, EXIT, ZoneParams, ZonePresence

NO_DWELL = np.array([-1])


def _run(presence: ZonePresence, probabilities: list[float], dwell: np.ndarray = NO_DWELL) -> list[tuple]:
    events = []
    for k, p in enumerate(probabilities):
        e = presence.update(np.array([3]), np.array([1000 * k]), np.array([[p]]), dwell)
        events += list(zip(e.kind.tolist(), e.t_ms.tolist(), strict=True))
    return events


def test_a_user_enters_when_sure_and_leaves_when_sure_of_the_opposite() -> None:
    """Each event is told when sure (0.8 in, 0.2 out) and stamped with the last crossing of one half."""
    presence = ZonePresence()
    told = []
    for k, p in enumerate([0.3, 0.6, 0.85, 0.5, 0.3, 0.15, 0.5, 0.9]):
        e = presence.update(np.array([3]), np.array([1000 * k]), np.array([[p]]), NO_DWELL)
        told += list(
            zip(e.kind.tolist(), e.t_ms.tolist(), e.told_ms.tolist(), e.probability.tolist(), strict=True)
        )
    assert told == [(ENTER, 1000, 2000, 0.85), (EXIT, 4000, 5000, 0.15), (ENTER, 6000, 7000, 0.9)]


def test_an_estimate_hovering_at_a_boundary_causes_no_event() -> None:
    flicker = [0.45, 0.55] * 20
    assert _run(ZonePresence(), flicker) == []
    naive = sum(1 for a, b in itertools.pairwise(flicker) if (a >= 0.5) != (b >= 0.5))
    assert naive == len(flicker) - 1  # a point-in-polygon test would have told every one


def test_a_dwell_fires_once_after_its_time_inside() -> None:
    events = _run(ZonePresence(), [0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 0.1, 0.9, 0.9], np.array([3000]))
    assert events == [(ENTER, 0), (DWELL, 3000), (EXIT, 6000), (ENTER, 7000)]
    assert _run(ZonePresence(), [0.9], np.array([0])) == [(ENTER, 0), (DWELL, 0)]


def test_users_and_zones_are_apart_and_rows_are_reused_without_events() -> None:
    presence = ZonePresence(ZoneParams(enter_probability=0.7, exit_probability=0.4))
    e = presence.update(
        np.array([0, 5]), np.array([10, 20]), np.array([[0.8, 0.1], [0.2, 0.75]]), np.array([-1, -1])
    )
    assert list(zip(e.row.tolist(), e.zone.tolist(), e.kind.tolist(), e.t_ms.tolist(), strict=True)) == [
        (0, 0, ENTER, 10),
        (5, 1, ENTER, 20),
    ]
    np.testing.assert_allclose(e.probability, [0.8, 0.75])
    presence.clear_rows(np.array([5]))  # the user left; another takes its row
    e = presence.update(np.array([5]), np.array([30]), np.array([[0.2, 0.0]]), np.array([-1, -1]))
    assert len(e) == 0
    presence.renumber_zones(np.array([1, -1, 0]))  # now: old zone 1, a new zone, old zone 0
    assert presence.inside[0].tolist() == [False, False, True]
    e = presence.update(np.array([0]), np.array([40]), np.array([[0.0, 0.0, 0.0]]), np.array([-1, -1, -1]))
    assert list(zip(e.zone.tolist(), e.kind.tolist(), strict=True)) == [(2, EXIT)]


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="stamp_probability"):
        ZoneParams(enter_probability=0.4, exit_probability=0.2)
    with pytest.raises(ValueError, match="stamp_probability < enter_probability"):
        ZoneParams(enter_probability=0.5, exit_probability=0.5)
    presence = ZonePresence()
    with pytest.raises(ValueError, match="one dwell time per zone"):
        presence.update(np.array([0]), np.array([0]), np.array([[0.5, 0.5]]), NO_DWELL)
    with pytest.raises(ValueError, match="distinct"):
        presence.update(np.array([1, 1]), np.array([0, 0]), np.array([[0.5], [0.5]]), NO_DWELL)
