"""Every user on a floor: the belief over the building's floors, and what the believed floor decides (the
anchors a detection joins, the users an encounter pairs, the fingerprints a scan is placed on)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slam_core.crowd.fingerprints import FingerprintParams
from slam_core.tracking.fingerprint_stage import FingerprintStage
from slam_core.tracking.floors import FloorParams, Floors
from slam_core.tracking.params import ColdStartParams
from slam_core.tracking.tracker import BuildingTracker, TrackerParams, UserBatch
from tests.slam_core.tracking.test_cold_start import walking_second
from tests.slam_core.tracking.test_encounters import CAL, _fix, _sighting

T0 = 1_700_000_000_000
STAIRS = 1


# ---------------------------------------------------------------------- the belief
def test_a_start_names_its_floor_and_a_rise_of_a_storey_moves_one_up() -> None:
    floors = Floors(FloorParams(), (2, 0, 1))  # any order: kept lowest first
    assert floors.levels == (0, 1, 2)
    p = floors.start(1)
    assert floors.believed(p) == (1, pytest.approx(0.999))
    up = floors.rise(p, 4.4)  # one storey of the default 4.5 m
    assert floors.believed(up)[0] == 2
    assert floors.believed(up)[1] > 0.95
    down_two = floors.rise(floors.start(2), -9.1)
    assert floors.believed(down_two)[0] == 0
    # the top floor going up: no floor that rise reaches, so it was no change of floor
    top = floors.believed(floors.rise(floors.start(2), 4.5))
    assert top == (2, pytest.approx(0.999, abs=1e-3))
    # an unknown rise (NaN) changes nothing
    np.testing.assert_array_equal(floors.rise(p, math.nan), p)


def test_the_operator_s_elevations_decide_how_far_a_rise_goes() -> None:
    floors = Floors(FloorParams(), (0, 1, 2), (0.0, 6.0, 9.5))  # a tall ground floor
    assert floors.believed(floors.rise(floors.start(0), 6.1))[0] == 1
    assert floors.believed(floors.rise(floors.start(1), 3.4))[0] == 2
    # a level without an elevation is a storey from the nearest one given
    partly = Floors(FloorParams(storey_m=4.0), (0, 1, 2), (0.0, math.nan, 10.0))
    np.testing.assert_allclose(partly.heights_m, [0.0, 4.0, 10.0])


def test_radio_evidence_moves_a_belief_slowly_and_unknown_floors_keep_their_share() -> None:
    floors = Floors(FloorParams(), (0, 1, 2))
    p = floors.start(0)
    evidence = np.array([-8.0, 0.0, math.nan])  # floor 1 explains the scan much better; floor 2 knows nothing
    steps = 0
    while floors.believed(p)[0] != 1:
        p = floors.weigh(p, evidence)
        steps += 1
        assert steps < 20
    assert steps > 1  # a start is not overturned by one scan
    assert floors.weigh(p, np.full(3, math.nan)) is p  # no evidence: no change
    assert floors.weigh(p, np.array([math.nan, -1.0, math.nan])) is p  # one floor alone compares nothing
    with pytest.raises(ValueError, match="one log-likelihood per level"):
        floors.weigh(p, np.zeros(2))


def test_a_level_the_building_does_not_have_is_named_with_the_ones_it_has() -> None:
    with pytest.raises(ValueError, match=r"no floor 7; the building's floors: -1, 0, 1"):
        Floors(FloorParams(), (-1, 0, 1)).start(7)
    with pytest.raises(ValueError, match="each once"):
        Floors(FloorParams(), (0, 0))
    with pytest.raises(ValueError, match="floor parameters"):
        FloorParams(storey_m=0.0)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.floats(-20.0, 20.0).map(lambda r: ("rise", r)),
            st.just(("maybe", None)),
            st.lists(st.one_of(st.floats(-50.0, 0.0), st.just(math.nan)), min_size=4, max_size=4).map(
                lambda ll: ("weigh", ll)
            ),
        ),
        max_size=30,
    )
)
def test_a_belief_stays_a_distribution(updates: list[tuple[str, object]]) -> None:
    floors = Floors(FloorParams(), (-1, 0, 1, 2))
    p = floors.start(0)
    for kind, value in updates:
        if kind == "maybe":
            p = floors.maybe_changed(p)
        else:
            p = floors.rise(p, value) if kind == "rise" else floors.weigh(p, np.array(value))  # type: ignore[arg-type]
        assert np.all(p >= 0.0)
        assert math.isclose(float(p.sum()), 1.0, rel_tol=1e-9)


# ---------------------------------------------------------------------- the tracker on floors
def _stairs(user: str, t_ms: int, rise_m: float) -> UserBatch:
    return UserBatch(
        user=user,
        detect_t=np.array([t_ms], dtype=np.int64),
        detect_type=np.array([STAIRS], dtype=np.int64),
        detect_rise=np.array([rise_m]),
    )


def _building(levels: tuple[int, ...] = (0, 1)) -> BuildingTracker:
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    tracker.set_levels(levels)
    return tracker


def test_estimates_say_the_floor_a_fix_named_and_a_fix_on_a_missing_floor_is_refused() -> None:
    tracker = _building()
    outcome = tracker.apply([_fix("up", (5.0, 5.0), T0, 1), _fix("down", (5.0, 5.0), T0, 0)])
    assert (outcome.estimates["up"].floor, outcome.estimates["down"].floor) == (1, 0)
    assert outcome.estimates["up"].floor_probability > 0.99
    assert tracker.filters.levels[tracker._users["up"].slot] == 1
    with pytest.raises(ValueError, match=r"no floor 3; the building's floors: 0, 1"):
        tracker.apply([_fix("lost", (5.0, 5.0), T0, 3)])
    assert "lost" not in tracker.users or not tracker.is_tracking("lost")


def test_a_one_floor_building_reports_floor_zero_as_before() -> None:
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    row = tracker.apply([_fix("a", (0.0, 0.0), T0, 0)]).estimates["a"]
    assert (row.floor, row.floor_probability) == (0, 1.0)


def test_two_phones_a_storey_apart_are_no_encounter() -> None:
    tracker = _building()
    tracker.apply([_fix("a", (0.0, 0.0), T0, 0), _fix("b", (1.0, 0.0), T0, 1), _fix("c", (1.0, 0.0), T0, 0)])
    through_ceiling = tracker.apply([_sighting("a", "b", T0 + 1_000, 1.0)])
    assert through_ceiling.encounters == []
    assert through_ceiling.detections == 1  # heard, and set aside
    same_floor = tracker.apply([_sighting("a", "c", T0 + 2_000, 1.0)])
    assert [(e.detection.user_a, e.detection.user_b) for e in same_floor.encounters] == [("a", "c")]
    (met,) = same_floor.encounters
    assert met.level == 0
    assert met.places is not None
    np.testing.assert_allclose(met.places, [0.0, 0.0, 1.0, 0.0], atol=0.5)  # where each was when they met


def test_stairs_with_a_rise_move_the_user_up_and_their_landing_is_an_anchor_of_the_floor_above() -> None:
    tracker = _building((0, 1, 2))
    tracker.apply([_fix("climber", (10.0, 0.0), T0, 0), _fix("resident", (10.0, 0.0), T0, 0)])
    outcome = tracker.apply([_stairs("climber", T0 + 5_000, 4.6)])
    assert outcome.estimates["climber"].floor == 1
    (landing,) = outcome.anchors_changed
    assert tracker.crowd.level(landing) == 1
    # stairs found downstairs at the same place are another anchor: floor 0's
    downstairs = tracker.apply([_stairs("resident", T0 + 6_000, math.nan)])
    (other,) = downstairs.anchors_changed
    assert other != landing
    assert tracker.crowd.level(other) == 0
    assert downstairs.estimates["resident"].floor == 0  # a detection without a rise is no change of floor


def test_a_user_s_floor_survives_a_snapshot_and_levels_that_go_take_their_share() -> None:
    import pickle

    tracker = _building((0, 1, 2))
    tracker.apply([_fix("a", (0.0, 0.0), T0, 2)])
    again = pickle.loads(pickle.dumps(tracker))
    again.set_levels((0, 1, 2))
    assert again.floor_of("a")[0] == 2
    again.set_levels((0, 1))  # floor 2 taken away: the user starts over, unsure
    level, p = again.floor_of("a")
    assert p == pytest.approx(0.5)
    assert again.filters.levels[again._users["a"].slot] == level


# ---------------------------------------------------------------------- the floors' fingerprints
def _scan(floor: int, x: float, rng: np.random.Generator) -> tuple[list[str], np.ndarray]:
    """A scan at (x, 0) on a floor: its own APs strong along a 60 m corridor, the other floor's 15 dB weaker
    through the ceiling."""
    names, rss = [], []
    for level in (0, 1):
        for i, ax in enumerate(np.linspace(0.0, 60.0, 7)):
            loss = 0.0 if level == floor else 15.0
            names.append(f"0a:00:00:00:{level:02x}:{i:02x}")
            rss.append(-40.0 - 25.0 * math.log10(max(abs(ax - x), 1.0)) - loss + rng.normal(0.0, 2.0))
    return names, np.array(rss)


def _floor_maps(tracker: BuildingTracker, rng: np.random.Generator, xs: np.ndarray) -> None:
    scans = [_scan(level, x, rng) for level in (0, 1) for x in xs]  # one survey of both floors
    tracker.load_radio_map(
        "survey",
        np.tile(np.column_stack([xs, np.zeros_like(xs)]), (2, 1)),
        [s[0] for s in scans],
        [s[1] for s in scans],
        np.full(2 * xs.size, T0 - 3_600_000, dtype=np.int64),
        np.repeat([0, 1], xs.size),
    )


def test_each_floor_s_map_says_how_well_it_explains_a_scan_near_the_user() -> None:
    rng = np.random.default_rng(5)
    stage = FingerprintStage(FingerprintParams(enabled=True, min_references=10), 3_000)
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    tracker.set_levels((0, 1))
    tracker.fingerprints = stage
    _floor_maps(tracker, rng, np.arange(0.0, 30.0, 2.0))  # the crowd walked the corridor's west half
    names, rss = _scan(1, 12.0, rng)
    ll = stage.floor_evidence((0, 1), -3, names, rss, np.array([12.0, 0.0]))
    assert ll[1] > ll[0]
    anywhere = stage.floor_evidence((0, 1), -3, names, rss, None)
    assert anywhere[1] > anywhere[0]
    # where no one walked, no floor says anything
    assert np.isnan(stage.floor_evidence((0, 1), -3, names, rss, np.array([55.0, 0.0]))).all()


def test_a_phone_without_a_fix_finds_its_floor_first() -> None:
    rng = np.random.default_rng(6)
    params = TrackerParams(
        fingerprints=FingerprintParams(enabled=True, min_references=10),
        cold_start=ColdStartParams(enabled=True, confident_sigma_m=5.0),
    )
    tracker = BuildingTracker(params, CAL, seed=1)
    tracker.set_levels((0, 1))
    _floor_maps(tracker, rng, np.arange(0.0, 60.0, 2.0))
    x = 10.0
    for k in range(20):
        x += 1.4
        tracker.apply([walking_second("upstairs", k, *_scan(1, x, rng))])
    level, p = tracker.floor_of("upstairs")
    assert level == 1
    assert p > 0.9
    assert tracker.filters.levels[tracker._users["upstairs"].slot] == 1


# ---------------------------------------------------------------------- ways between floors
def test_a_way_seen_without_its_rise_spreads_the_belief_to_the_adjacent_floors() -> None:
    floors = Floors(FloorParams(unmeasured_change=0.3), (0, 1, 2))
    middle = floors.maybe_changed(np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(middle, [0.15, 0.7, 0.15])
    bottom = floors.maybe_changed(np.array([1.0, 0.0, 0.0]))  # the only neighbour takes it all
    np.testing.assert_allclose(bottom, [0.7, 0.3, 0.0])
    assert floors.believed(middle)[0] == 1  # the radio, not the detection, moves the believed floor
    single = Floors(FloorParams(), (0,))
    np.testing.assert_array_equal(single.maybe_changed(np.ones(1)), np.ones(1))


def _walking_with_barometer(
    user: str, t0: int, seconds: int, height: np.ndarray, azimuth: float = math.pi / 2
) -> list[UserBatch]:
    """One-second batches of a phone that counts its own steps (two a second) and sends its barometer at
    5 Hz; ``height`` (m) per 0.2 s sample."""
    from slam_core.sensing.pdr.online import ImuSamples
    from slam_core.sim.storeys import pressure_at

    out = []
    for s in range(seconds):
        t = t0 + s * 1_000 + np.arange(5) * 200
        hpa = pressure_at(height[s * 5 : s * 5 + 5], np.full(5, 1010.0))
        out.append(
            UserBatch(
                user=user,
                step_t=np.array([t[0] + 100, t[0] + 600], dtype=np.int64),
                step_length=np.full(2, 0.3),
                step_azimuth=np.full(2, azimuth),
                step_turn=np.full(2, math.nan),
                imu=ImuSamples(acc=np.zeros((0, 4)), pressure=np.column_stack([t, hpa])),
            )
        )
    return out


def test_a_phone_that_counts_its_own_steps_climbs_by_its_barometer() -> None:
    tracker = _building((0, 1, 2))
    tracker.apply([_fix("climber", (0.0, 0.0), T0, 0)])
    assert not tracker.front_end.has_barometer("climber")
    # 5 s on the landing, 15 s up a flight of 4.5 m, 8 s on the floor above
    height = np.concatenate([np.zeros(25), np.linspace(0.0, 4.5, 75), np.full(40, 4.5)])
    floors = []
    for batch in _walking_with_barometer("climber", T0 + 1_000, 28, height):
        outcome = tracker.apply([batch])
        floors.append(outcome.estimates["climber"].floor)
    assert floors[:19] == [0] * 19  # not before it arrived (t = 20 s)
    assert floors[-1] == 1
    arrived = floors.index(1)
    assert arrived <= 19 + 5  # within 5 s of arriving
    assert tracker.front_end.has_barometer("climber")
    assert tracker.front_end.fired["stairs"] == 1
    # a phone with a barometer passing stairs with no change of height stays where it is, sure of it
    outcome = tracker.apply([_stairs("climber", T0 + 40_000, math.nan)])
    assert (outcome.estimates["climber"].floor, outcome.estimates["climber"].floor_probability > 0.9) == (
        1,
        True,
    )


def test_an_escalator_carries_its_rider_along_the_way_they_faced() -> None:
    from slam_core.filter.params import BuildingAnchorParams, FilterParams, extended_confusion

    n_types = len(extended_confusion(10))
    params = TrackerParams(
        filter=FilterParams(anchors=BuildingAnchorParams(confusion=extended_confusion(n_types)))
    )
    tracker = BuildingTracker(params, CAL, seed=0)
    tracker.set_levels((0, 1))
    tracker.apply([_fix("rider", (0.0, 0.0), T0, 0)])
    tracker.apply(
        [
            UserBatch(
                user="rider",
                step_t=np.array([T0 + 500, T0 + 1_000], dtype=np.int64),
                step_length=np.full(2, 0.7),
                step_azimuth=np.full(2, math.pi / 2),  # east
                step_turn=np.full(2, math.nan),
            )
        ]
    )
    before = tracker.estimate("rider")
    assert before is not None
    escalator = tracker._escalator_type
    outcome = tracker.apply(
        [
            UserBatch(
                user="rider",
                detect_t=np.array([T0 + 20_000], dtype=np.int64),
                detect_type=np.array([escalator], dtype=np.int64),
                detect_rise=np.array([4.5]),
            )
        ]
    )
    after = outcome.estimates["rider"]
    assert after.floor == 1
    assert after.x - before.x == pytest.approx(4.5 / math.tan(math.radians(30.0)), abs=1.5)
    assert abs(after.y - before.y) < 1.0


def test_the_crowd_measures_the_storeys_and_two_low_storeys_are_then_two() -> None:
    floors = Floors(FloorParams(), (0, 1, 2))  # no elevations given: 4.5 m storeys until measured
    assert floors.believed(floors.rise(floors.start(0), 6.2))[0] == 1  # two 3.1 m storeys look like one
    learned = 0
    for k in range(5):
        before = floors.start(k % 2)  # up from 0 to 1, then from 1 to 2, ...
        after = floors.rise(before, 3.1)
        learned += floors.learn(before, after, 3.1)
    assert learned == 5
    np.testing.assert_allclose(floors.heights_m, [0.0, 3.1, 6.2], atol=1e-9)
    assert floors.believed(floors.rise(floors.start(0), 6.2))[0] == 2
    # not learned: unsure before, two levels at once, the wrong way, or far from the gap as known
    unsure = np.array([0.5, 0.5, 0.0])
    assert not floors.learn(unsure, floors.rise(unsure, 3.1), 3.1)
    assert not floors.learn(floors.start(0), floors.start(2), 6.2)
    assert not floors.learn(floors.start(0), floors.start(1), -3.1)
    assert not floors.learn(floors.start(0), floors.start(1), 9.0)
    # the operator's elevations are not learned over; what was learned survives new floors
    given = Floors(FloorParams(), (0, 1), (0.0, 5.0))
    assert not given.learn(given.start(0), given.start(1), 3.0)
    more = Floors(FloorParams(), (0, 1, 2, 3))
    more.adopt(floors)
    np.testing.assert_allclose(more.heights_m, [0.0, 3.1, 6.2, 9.3], atol=1e-9)  # the learned storey above


def test_one_measured_gap_sets_the_storey_for_the_others() -> None:
    floors = Floors(FloorParams(storey_learning_min=2), (0, 1, 3))  # level 2 is not in the building
    for _ in range(2):
        floors.learn(floors.start(0), floors.start(1), 4.0)
    np.testing.assert_allclose(floors.heights_m, [0.0, 4.0, 12.0])  # 1 -> 3 spans two storeys of 4 m


def test_a_phone_that_finds_its_own_floor_changes_is_not_moved_twice_by_its_barometer() -> None:
    tracker = _building((0, 1, 2))
    tracker.apply([_fix("sdk", (0.0, 0.0), T0, 0)])
    height = np.concatenate([np.zeros(25), np.linspace(0.0, 4.5, 75), np.full(40, 4.5)])
    batches = _walking_with_barometer("sdk", T0 + 1_000, 28, height)
    # the phone's own detector reports the flight as stairs with its rise, in the batch where it ends
    landing = batches[20]
    batches[20] = replace(
        landing,
        detect_t=np.array([int(landing.step_t[-1])], dtype=np.int64),
        detect_type=np.array([STAIRS], dtype=np.int64),
        detect_rise=np.array([4.5]),
    )
    for batch in batches:
        outcome = tracker.apply([batch])
    assert outcome.estimates["sdk"].floor == 1  # one storey, not two
    assert tracker.front_end.fired["stairs"] == 1  # the server's detector saw it and kept it to itself


def _copies(tracker: BuildingTracker, user: str, anchor: int) -> np.ndarray:
    """The user's particles' own copies of a crowd anchor (one row a particle)."""
    s, slot = tracker.filters.state, tracker._users[user].slot
    particles, k = np.nonzero(s.map_crowd_id[slot] == anchor)
    return s.map_mu[slot, particles, k]


def test_a_floor_s_crowd_map_is_solved_on_its_own_and_only_its_users_take_it() -> None:
    """The joint solve runs on the floors whose anchors changed, at most once a period each; the particles of
    a floor that was not solved keep their own copies of its anchors."""
    tracker = BuildingTracker(TrackerParams(), CAL, seed=0)
    tracker.set_levels((0, 1))
    tracker.apply([_fix("down", (0.0, 0.0), T0, 0), _fix("up", (0.0, 0.0), T0, 1)])
    crowd, graph = tracker.crowd, tracker.graph
    anchors = {}
    for user, level in ((7, 0), (8, 1)):  # an anchor a floor, each detected 12 m east of a start at (0, 0)
        anchors[level] = crowd.contribute(user, np.array([10.0, 0.0]), np.eye(2), 1, T0, level=level)
        graph.add_user(user, np.zeros(2))
        graph.add_detection(user, anchors[level], np.array([12.0, 0.0]), 12.0)
    for name, level in (("down", 0), ("up", 1)):
        slot = np.array([tracker._users[name].slot])
        tracker.filters.merge_crowd_map(slot, crowd.snapshot(level))
        np.testing.assert_allclose(_copies(tracker, name, anchors[level]), [[10.0, 0.0]] * 75)
    changed = {anchors[1]}
    tracker._solve_crowd_map(changed, T0 + 10_000)
    solved = crowd.anchor(anchors[1])[0]
    assert solved[0] > 11.0  # the floor's detection moved it
    np.testing.assert_allclose(_copies(tracker, "up", anchors[1]), [solved] * 75)
    np.testing.assert_allclose(crowd.anchor(anchors[0])[0], [10.0, 0.0])  # the other floor: untouched
    np.testing.assert_allclose(_copies(tracker, "down", anchors[0]), [[10.0, 0.0]] * 75)
    assert tracker._last_solve_ms == {1: T0 + 10_000}
    tracker._solve_crowd_map({anchors[1]}, T0 + 12_000)  # within its period: not again
    assert tracker._last_solve_ms == {1: T0 + 10_000}
    tracker._solve_crowd_map({anchors[0]}, T0 + 12_000)  # the other floor's first
    assert tracker._last_solve_ms == {0: T0 + 12_000, 1: T0 + 10_000}
    assert crowd.anchor(anchors[0])[0][0] > 11.0
