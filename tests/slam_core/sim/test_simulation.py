"""The simulator reads the scenario as given and produces plausible, deterministic phone data."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slam_core.sim.simulation import Scenario, count_walls, room_zones, simulate
from slam_core.zones.geometry import points_inside, zone_set
from tests.conftest import TESTBED


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return Scenario.from_dict(json.loads(TESTBED.read_text()))


@pytest.fixture(scope="module")
def sim(scenario: Scenario):  # type: ignore[no-untyped-def]
    return simulate(scenario, 0)


def test_same_seed_same_world(scenario: Scenario) -> None:
    a, b = simulate(scenario, 3), simulate(scenario, 3)
    np.testing.assert_array_equal(a.world.anchor_xy, b.world.anchor_xy)
    np.testing.assert_array_equal(a.users[5].step_heading_obs, b.users[5].step_heading_obs)
    assert not np.array_equal(simulate(scenario, 4).world.anchor_xy, a.world.anchor_xy)


def test_world_follows_the_scenario(scenario: Scenario, sim) -> None:  # type: ignore[no-untyped-def]
    w = sim.world
    assert w.anchor_xy.shape == (30, 2)
    assert w.anchor_known.sum() == 3
    assert np.all(w.anchor_known[:3])
    gaps = np.linalg.norm(w.anchor_xy[:, None] - w.anchor_xy[None], axis=2) + np.eye(30) * 1e9
    assert gaps.min() >= 5.0
    on_corridor = (np.abs(w.anchor_xy % 10.0) < 1e-9) | (np.abs(w.anchor_xy % 10.0 - 10.0) < 1e-9)
    assert np.all(on_corridor.any(axis=1))
    assert w.ap_xy.shape == (40, 2)
    assert abs(float(w.shadow.std()) - 4.0) < 0.2


def test_users_walk_the_corridors(scenario: Scenario, sim) -> None:  # type: ignore[no-untyped-def]
    assert len(sim.users) == 23
    for tr in sim.users:
        steps = np.linalg.norm(np.diff(tr.xy, axis=0), axis=1)
        assert 245.0 < steps.sum() <= 250.0 + 1e-9  # 250 m of corridor; steps cut the corners slightly
        assert 0.0 <= tr.start_t <= 30.0
        near_line = np.minimum(np.abs(tr.xy - np.round(tr.xy / 10) * 10), 10).min(axis=1)
        assert np.all(near_line < 1e-6)  # on a corridor centre line
        assert np.all(np.diff(tr.t) > 0)


def test_observations_carry_the_noise_model(sim) -> None:  # type: ignore[no-untyped-def]
    tr = sim.users[0]
    assert np.all(tr.step_length_obs > 0)
    assert 8 <= sim.anchors_passed_per_user <= 15  # the paper's testbed: about 10
    heard = sim.users[0].scan_rss[~np.isnan(sim.users[0].scan_rss)]
    assert heard.size > 0
    assert np.all((heard >= -95.0) & (heard <= 0.0))
    assert np.all((sim.bt_rss >= -95.0) & (sim.bt_rss <= 0.0))
    assert np.all(sim.bt_pair[:, 0] != sim.bt_pair[:, 1])


def test_walls_are_counted_between_rooms(sim) -> None:  # type: ignore[no-untyped-def]
    w = sim.world
    along_corridor = count_walls(w, np.array([[1.0, 10.0]]), np.array([[39.0, 10.0]]))
    across_a_room = count_walls(w, np.array([[15.0, 0.0]]), np.array([[15.0, 10.0]]))
    assert along_corridor[0] == 0
    assert across_a_room[0] == 2  # out of the lower corridor's edge, into the upper one's


@pytest.mark.parametrize(
    ("patch", "message"),
    [
        (lambda raw: raw.pop("wifi"), "lacks the 'wifi' section"),
        (lambda raw: raw["floor"].update(corridors="maze"), "grid"),
        (lambda raw: raw["building_anchors"].update(type_confusion=[[1.0]]), "type_confusion"),
    ],
)
def test_bad_scenarios_are_rejected(patch, message: str) -> None:  # type: ignore[no-untyped-def]
    raw = json.loads(TESTBED.read_text())
    patch(raw)
    with pytest.raises(ValueError, match=message):
        Scenario.from_dict(raw)


def test_one_setting_changes_in_a_copy(scenario: Scenario) -> None:
    fewer = scenario.with_setting("users", "count", 2)
    assert fewer["users"]["count"] == 2
    assert scenario["users"]["count"] == 23  # the given scenario is untouched
    assert fewer["wifi"] == scenario["wifi"]
    with pytest.raises(KeyError, match="no section 'lobby'"):
        scenario.with_setting("lobby", "count", 2)
    with pytest.raises(ValueError, match="corridor"):  # the copy is validated like any scenario
        scenario.with_setting("floor", "corridors", "ring")


def test_a_room_zone_holds_the_corridors_in_front_of_the_room() -> None:
    sim = simulate(Scenario.from_dict(json.loads(TESTBED.read_text())), 0)
    ids, rings, levels = room_zones(sim.world)
    assert len(ids) == len(set(ids)) == 30  # 6 x 5 rooms between the corridors every 10 m of 60 x 50 m
    assert set(levels) == {0}
    zones = zone_set(rings, levels)
    # every true position is on a corridor: in front of one room at least, four at a crossing
    xy = np.concatenate([u.xy for u in sim.users])
    counts = points_inside(zones, xy[:, 0], xy[:, 1], np.zeros(len(xy), dtype=np.int64)).sum(axis=1)
    assert counts.min() >= 1
    assert counts.max() == 4
    assert ids[0] == "L0-0-0"
    np.testing.assert_allclose(rings[0], [[-3, -3], [13, -3], [13, 13], [-3, 13]])
