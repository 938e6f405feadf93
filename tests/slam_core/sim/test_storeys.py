"""The simulated building of several storeys: its ways between floors, the walks that take them, the radio
through its floors and the barometer that sees them, all as the scenario gives them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from server.data import shipped_scenario
from slam_core.sensing.vertical import pressure_height
from slam_core.sim.simulation import Scenario, Simulation, simulate, wifi_rss
from slam_core.sim.storeys import pressure_at


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return Scenario.from_dict(json.loads(shipped_scenario("three-floors").read_text()))


@pytest.fixture(scope="module")
def sim(scenario: Scenario) -> Simulation:
    return simulate(scenario.with_setting("users", "count", 24), 0)


def test_every_floor_has_its_own_anchors_and_access_points(scenario: Scenario, sim: Simulation) -> None:
    w = sim.world
    assert w.levels == 3
    np.testing.assert_array_equal(w.elevations, scenario["storeys"]["elevations_m"])
    per_floor = scenario["building_anchors"]["count"]
    np.testing.assert_array_equal(np.bincount(w.anchor_levels()), [per_floor] * 3)
    for level in range(3):
        mine = w.anchor_levels() == level
        assert w.anchor_known[mine].sum() == scenario["building_anchors"]["known_positions"]
    assert w.ap_level is not None
    np.testing.assert_array_equal(np.bincount(w.ap_level), [scenario["wifi"]["access_points"]] * 3)
    assert w.links is not None
    assert len({w.links.stairs, w.links.lift, w.links.escalator_foot, w.links.escalator_top}) == 4


def test_users_change_floors_only_by_the_ways_and_the_floor_changes_at_arrival(sim: Simulation) -> None:
    ways: set[str] = set()
    for tr in sim.users:
        assert tr.level is not None
        assert tr.is_step is not None
        changes = np.flatnonzero(np.diff(tr.level)) + 1
        assert len(changes) == len(tr.transitions)
        for k, (arrival, was, now, way) in zip(changes, tr.transitions, strict=True):
            ways.add(way)
            assert tr.t[k] == pytest.approx(arrival)
            assert (tr.level[k - 1], tr.level[k]) == (was, now)
            assert tr.level_at(arrival - 1e-6) == was
            assert tr.level_at(arrival) == now
            if way != "lift":
                assert abs(now - was) == 1
        moved = np.linalg.norm(np.diff(tr.xy, axis=0), axis=1)
        assert np.all(moved[tr.is_step] <= 1.2 * 0.7 + 1e-9)  # steps (a last one takes up a sliver)
    assert ways == {"stairs", "lift", "escalator"}


def test_a_lift_ride_and_an_escalator_ride_take_no_step(sim: Simulation) -> None:
    w = sim.world
    for tr in sim.users:
        assert tr.is_step is not None
        assert tr.level is not None
        for arrival, was, now, way in tr.transitions:
            k = int(np.searchsorted(tr.t, arrival - 1e-9))  # the sample of arrival
            rise = abs(w.elevations[now] - w.elevations[was])
            if way == "lift":
                assert not tr.is_step[k - 1]
                assert np.allclose(tr.xy[k], tr.xy[k - 1])
            elif way == "escalator":
                assert not tr.is_step[k - 1]
                assert np.linalg.norm(tr.xy[k] - tr.xy[k - 1]) == pytest.approx(
                    rise / math.tan(math.radians(30))
                )
            else:
                assert tr.is_step[k - 1]


def test_a_barometer_sees_each_storey_through_the_weather(sim: Simulation) -> None:
    w = sim.world
    with_barometer = [tr for tr in sim.users if tr.pressure.size]
    assert 0.5 < len(with_barometer) / len(sim.users) < 1.0
    assert w.weather_hpa_per_s != 0.0
    checked = 0
    for tr in with_barometer:
        height = pressure_height(tr.pressure[:, 1])
        for arrival, was, now, _ in tr.transitions:
            before = height[(tr.pressure[:, 0] > arrival - 40) & (tr.pressure[:, 0] < arrival - 30)]
            after = height[(tr.pressure[:, 0] > arrival + 5) & (tr.pressure[:, 0] < arrival + 8)]
            if before.size and after.size and tr.level_at(arrival - 40) == was:
                rise = w.elevations[now] - w.elevations[was]
                assert float(after.mean() - before.mean()) == pytest.approx(rise, abs=0.6)
                checked += 1
    assert checked >= 3
    # the inverse of the height the detector reads
    np.testing.assert_allclose(
        pressure_height(pressure_at(np.array([0.0, 4.5]), np.full(2, 1013.25))), [0, 4.5]
    )


def test_a_floor_s_access_point_is_heard_louder_on_its_floor(sim: Simulation, scenario: Scenario) -> None:
    w = sim.world
    assert w.ap_level is not None
    quiet = dict(scenario["wifi"], scan_noise_sigma_db=0.0, sensitivity_dbm=-200.0)
    rng = np.random.default_rng(0)
    xy = np.array([20.0, 20.0])
    on_0 = wifi_rss(w, quiet, xy, rng, level=0)
    on_2 = wifi_rss(w, quiet, xy, rng, level=2)
    floor_0 = w.ap_level == 0
    assert np.median(on_0[floor_0] - on_2[floor_0]) > 2 * scenario["storeys"]["floor_loss_db"]


def test_phones_without_a_barometer_report_the_ways_their_accelerometer_finds(sim: Simulation) -> None:
    found = [d for tr in sim.users if not tr.pressure.size for d in tr.way_detections]
    assert found
    assert all(tr.way_detections == () for tr in sim.users if tr.pressure.size)
    lifts = [rise for _, kind, rise in found if kind == 0 and math.isfinite(rise)]
    stairs = [rise for _, kind, rise in found if kind != 0]
    assert all(math.isnan(r) for r in stairs)  # stairs without a direction
    assert all(3.0 < abs(r) < 12.0 for r in lifts)


def test_a_storey_section_that_does_not_stack_is_refused(scenario: Scenario) -> None:
    raw = json.loads(json.dumps(scenario.raw))
    raw["storeys"]["elevations_m"] = [0.0, 5.0, 4.0]
    with pytest.raises(ValueError, match="each above the one below"):
        Scenario.from_dict(raw)
    raw["storeys"]["elevations_m"] = [0.0, 5.0]
    raw["storeys"]["take_probability"] = 1.5
    with pytest.raises(ValueError, match="take_probability"):
        Scenario.from_dict(raw)


def test_the_one_floor_testbed_has_one_floor(sim: Simulation) -> None:
    from tests.conftest import TESTBED

    one = simulate(Scenario.from_dict(json.loads(TESTBED.read_text())).with_setting("users", "count", 3), 0)
    assert one.world.levels == 1
    assert one.world.links is None
    assert all(tr.level is None and tr.level_at(1e9) == 0 and not tr.pressure.size for tr in one.users)
