"""The tracker's zones: events for the users a call estimates, by their particles, on their floor."""

from __future__ import annotations

import numpy as np
import pytest

from slam_core.tracking.tracker import BuildingTracker, TrackerParams
from tests.slam_core.tracking.test_encounters import CAL, T0, _fix

SHOP = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])


def _tracker() -> BuildingTracker:
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    tracker.set_levels((0, 1))
    tracker.zones.set_zones(["shop", "dwell"], [SHOP, SHOP + 20.0], [0, 0], [None, 5_000])
    return tracker


def test_a_user_placed_in_a_zone_enters_it_and_leaves_when_placed_far_away() -> None:
    tracker = _tracker()
    out = tracker.apply([_fix("a", (5.0, 5.0), T0), _fix("up", (5.0, 5.0), T0, 1)])
    assert [(e.user, e.zone_id, e.kind, e.t_ms) for e in out.zone_events] == [("a", "shop", "enter", T0)]
    assert out.zone_events[0].probability > 0.99
    out = tracker.apply([_fix("a", (45.0, 5.0), T0 + 1_000)])  # a fix far off: the cloud moves there
    assert [(e.zone_id, e.kind) for e in out.zone_events] == [("shop", "exit")]


def test_a_dwell_fires_once_and_a_forgotten_user_is_in_no_zone() -> None:
    tracker = _tracker()
    kinds = []
    for k in range(8):
        out = tracker.apply([_fix("b", (25.0, 25.0), T0 + 1_000 * k)])
        kinds += [(e.kind, e.t_ms - T0) for e in out.zone_events]
    assert kinds == [("enter", 0), ("dwell", 5_000)]
    slot = tracker._users["b"].slot
    tracker.remove_user("b")
    assert not tracker.zones.presence.inside[slot].any()


def test_zones_are_replaced_by_id_and_a_bad_outline_changes_nothing() -> None:
    tracker = _tracker()
    tracker.apply([_fix("a", (5.0, 5.0), T0)])
    bowtie = np.array([[0.0, 0.0], [4.0, 4.0], [4.0, 0.0], [0.0, 4.0]])
    with pytest.raises(ValueError, match="zone 'bad': the outline crosses itself"):
        tracker.zones.set_zones(["shop", "bad"], [SHOP, bowtie], [0, 0], [None, None])
    assert tracker.zones.ids == ["shop", "dwell"]
    with pytest.raises(ValueError, match="each zone id once"):
        tracker.zones.set_zones(["shop", "shop"], [SHOP, SHOP], [0, 0], [None, None])
    tracker.zones.set_zones(["new", "shop"], [SHOP + 100.0, SHOP], [0, 0], [None, None])
    out = tracker.apply([_fix("a", (5.0, 6.0), T0 + 1_000)])
    assert out.zone_events == []  # still inside the kept zone: no second entry
    tracker.zones.set_zones([], [], [], [])
    assert tracker.apply([_fix("a", (50.0, 6.0), T0 + 2_000)]).zone_events == []
