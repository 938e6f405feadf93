"""Encounters in the live tracker: Bluetooth sightings between tracked phones become human anchors when the
filters place the pair close (``slam_core.encounters.selection``); the rest are counted, not applied."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

import slam_core.tracking.encounter_stage as encounter_stage
from slam_core.encounters.models import Calibration, RangeModel
from slam_core.filter.params import FilterParams
from slam_core.tracking.tracker import BuildingTracker, TrackerOutcome, TrackerParams, UserBatch

T0 = 1_700_000_000_000
BT = RangeModel("bt-quadratic", (-60.0, -22.0 / math.log(10.0), 0.0), 2.8)
CAL = Calibration(RangeModel("wifi-log", (0.0, 2.0), 3.0), BT)


def _fix(user: str, xy: tuple[float, float], t_ms: int, level: int = 0) -> UserBatch:
    return UserBatch(
        user=user,
        ble_id=f"ble-{user}",
        fix_t=np.array([t_ms], dtype=np.int64),
        fix_xy=np.array([xy], dtype=float),
        fix_sigma=np.array([0.5]),
        fix_azimuth=np.array([0.0]),
        fix_level=np.array([level], dtype=np.int64),
    )


def _sighting(user: str, peer: str, t_ms: int, distance_m: float) -> UserBatch:
    rss = float(BT.feature_at(np.array([distance_m]))[0])
    return UserBatch(
        user=user,
        ble_id=f"ble-{user}",
        peer_t=np.array([t_ms], dtype=np.int64),
        peer_id=(f"ble-{peer}",),
        peer_rss=np.array([rss]),
    )


def _tracker(**filter_changes: object) -> BuildingTracker:
    params = TrackerParams(filter=replace(FilterParams(), **filter_changes))  # type: ignore[arg-type]
    tracker = BuildingTracker(params, CAL, seed=0)
    tracker.apply([_fix("a", (0.0, 0.0), T0), _fix("b", (4.0, 0.0), T0), _fix("c", (40.0, 0.0), T0)])
    return tracker


def _applied(outcome: TrackerOutcome) -> list[tuple[str, str, bool]]:
    return [(e.detection.user_a, e.detection.user_b, e.applied) for e in outcome.encounters]


def test_a_close_pair_is_applied_and_then_cools_down() -> None:
    tracker = _tracker()
    before, peer_before = tracker.estimate("a"), tracker.estimate("b")
    outcome = tracker.apply([_sighting("a", "b", T0 + 1_000, 3.0)])
    assert outcome.detections == 1
    assert _applied(outcome) == [("a", "b", True)]
    # one estimate per applied batch: the peer's moved filter is estimated with its own next batch
    assert list(outcome.estimates) == ["a"]
    after = tracker.estimate("a")
    assert before is not None
    assert after is not None
    # the covariance shrinks along the pair's axis (x): the range measures it
    assert after.cov[0] < before.cov[0]
    assert after.cov[0] > 0
    assert after.cov[2] > 0
    assert after.cov[0] * after.cov[2] > after.cov[1] ** 2
    # within the cooldown the pair is detected, not applied again
    again = tracker.apply([_sighting("b", "a", T0 + 3_000, 3.0)])
    assert peer_before is not None
    assert again.estimates["b"].cov[0] < peer_before.cov[0]  # the first call's encounter had moved b too
    assert again.detections == 1
    assert again.encounters == []
    later = tracker.apply([_sighting("b", "a", T0 + 6_000, 3.0)])  # a heard 5 s ago: still placed
    assert _applied(later) == [("b", "a", True)]


def test_a_pair_the_filters_place_far_apart_is_not_chosen_whatever_it_reads() -> None:
    """'c' is 40 m from 'a' by the filters; a strong reading (1 m) is counted but not applied: the choice
    does not depend on the reading, so a lucky or forged strong reading cannot pull users together."""
    tracker = _tracker()
    before = tracker.estimate("c")
    outcome = tracker.apply([_sighting("a", "c", T0 + 1_000, 1.0)])
    assert outcome.detections == 1
    assert outcome.encounters == []
    after = tracker.estimate("c")
    assert before is not None
    assert after is not None
    assert (after.x, after.y) == (before.x, before.y)


def test_without_human_anchors_encounters_are_reported_not_applied() -> None:
    tracker = _tracker(use_human_anchors=False)
    before = tracker.estimate("a")
    outcome = tracker.apply([_sighting("a", "b", T0 + 1_000, 3.0)])
    assert _applied(outcome) == [("a", "b", False)]
    after = tracker.estimate("a")
    assert before is not None
    assert after is not None
    assert after.cov == before.cov


def test_sightings_of_untracked_or_unknown_phones_are_not_encounters() -> None:
    tracker = _tracker()
    unknown = tracker.apply([_sighting("a", "nobody", T0 + 1_000, 2.0)])
    assert unknown.detections == 0
    assert unknown.encounters == []
    untracked = tracker.apply([_sighting("d", "a", T0 + 1_000, 2.0)])  # 'd' has no fix yet
    assert untracked.detections == 1
    assert untracked.encounters == []


def test_forgotten_users_free_their_slots_and_are_no_longer_heard() -> None:
    import pytest

    tracker = _tracker()
    slots = tracker.filters.active_users.size
    tracker.remove_users(["a", "c"])
    assert tracker.users == ["b"]
    assert tracker.filters.active_users.size == slots - 2
    # "b" hears "a"'s phone: not an encounter any more, "a" is unknown until its next fix
    outcome = tracker.apply([_sighting("b", "a", T0 + 1_000, 2.0)])
    assert outcome.detections == 0
    assert not tracker.is_tracking("a")
    with pytest.raises(KeyError, match="unknown users"):
        tracker.remove_users(["b", "nobody"])
    assert tracker.users == ["b"]  # nothing was removed
    tracker.apply([_fix("a", (1.0, 0.0), T0 + 2_000)])  # a new fix brings "a" back, in a free slot
    assert tracker.is_tracking("a")
    assert tracker.filters.active_users.size == slots - 1


def _walk_with_scans(user: int, t_ms: int, rng: np.random.Generator, scan_lag_ms: int = 0) -> UserBatch:
    """Two steps east and a scan (``scan_lag_ms`` before the second step) of 8 of 12 APs whose levels follow
    the user's row (users on one row hear alike, so their scans meet by Eq. 3)."""
    levels = -45.0 - 3.0 * np.arange(12) - 2.0 * (user % 3) + rng.normal(0.0, 1.0, 12)
    heard = np.sort(rng.choice(12, size=8, replace=False))
    return UserBatch(
        user=f"u{user}",
        ble_id=f"ble-u{user}",
        step_t=np.array([t_ms - 500, t_ms], dtype=np.int64),
        step_length=np.array([0.7, 0.7]),
        step_azimuth=np.array([math.pi / 2, math.pi / 2]),
        step_turn=np.full(2, math.nan),
        scan_t=np.array([t_ms - scan_lag_ms], dtype=np.int64),
        scan_offsets=np.array([0, heard.size], dtype=np.int64),
        scan_bssid=tuple(f"ap{i:02d}" for i in heard),
        scan_rss=np.round(levels[heard], 1),
        scan_last_seen=np.full(heard.size, -1, dtype=np.int64),
    )


def _busy_building(
    background_scans: int, monkeypatch: pytest.MonkeyPatch, scan_lag_ms: int = 0, calls_per_second: int = 1
) -> list[object]:
    """24 phones posting a second each, in ``calls_per_second`` calls (the later ones' peers lag)."""
    monkeypatch.setattr(encounter_stage, "BACKGROUND_SCANS", background_scans)
    tracker = BuildingTracker(TrackerParams(), CAL, seed=3)
    tracker.apply([_fix(f"u{k}", (2.0 * (k % 3), 1.5 * (k // 3)), T0) for k in range(24)])
    rng = np.random.default_rng(7)
    seen: list[object] = []
    for second in range(1, 8):
        batches = [_walk_with_scans(k, T0 + 1_000 * second + 20 * k, rng, scan_lag_ms) for k in range(24)]
        for part in np.array_split(np.arange(24), calls_per_second):
            outcome = tracker.apply([batches[k] for k in part])
            seen.append(outcome.detections)
            seen += [
                (e.detection.user_a, e.detection.user_b, e.detection.feature, e.applied)
                for e in outcome.encounters
            ]
            seen += [(u, r.x, r.y, *r.cov) for u, r in sorted(outcome.estimates.items())]
    return seen


def test_scans_compared_on_a_thread_change_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    """A busy call compares its scans on a thread beside the rounds and fixes: the same detections,
    encounters and estimates, bit for bit, as compared inline."""
    inline = _busy_building(10**9, monkeypatch)
    threaded = _busy_building(1, monkeypatch)
    assert sum(n for n in inline if isinstance(n, int)) > 50  # the rows' scans do meet
    assert any(isinstance(x, tuple) and len(x) == 4 and x[3] for x in inline)  # and encounters are applied
    assert threaded == inline


def _looked_up(tracker: BuildingTracker) -> list[int]:
    """Each detector user id's slot, looked up afresh (what ``DetectorSlots`` keeps)."""
    detector = tracker.encounters.detector
    tracks = [tracker._users.get(detector.user_name(i)) for i in range(detector.n_user_ids)]
    return [u.slot if u is not None and u.slot >= 0 else -1 for u in tracks]


def test_detector_slots_follow_starts_removals_and_returns() -> None:
    """The slots kept for the detector's user ids between calls equal a fresh lookup after every change:
    users heard before their fix, removed (their slot freed and reused), back again, and a tracker restored
    from a pickle."""
    import pickle

    tracker = _tracker()
    everyone = np.arange(0)

    def check() -> None:
        nonlocal everyone
        stage = tracker.encounters
        everyone = np.arange(stage.detector.n_user_ids)
        assert stage.slots.of(stage.detector, tracker._users, everyone).tolist() == _looked_up(tracker)

    tracker.apply([_sighting("a", "b", T0 + 1_000, 3.0), _sighting("d", "a", T0 + 1_000, 3.0)])
    check()  # 'd' is heard and named before it has a slot
    tracker.apply([_fix("d", (8.0, 0.0), T0 + 1_500)])
    check()  # 'd' started after its id was interned
    tracker.remove_users(["a", "c"])
    tracker.apply([_fix("e", (2.0, 0.0), T0 + 2_000)])  # takes a freed slot
    tracker.apply([_sighting("e", "b", T0 + 2_500, 3.0), _sighting("b", "d", T0 + 2_500, 3.0)])
    check()
    a = tracker.encounters.detector.known_user_id("a")
    assert a is not None
    assert _looked_up(tracker)[a] == -1  # removed
    tracker.apply([_fix("a", (1.0, 0.0), T0 + 3_000)])  # back, in another slot
    tracker.apply([_sighting("a", "e", T0 + 3_500, 3.0)])
    check()
    assert -1 not in _looked_up(tracker)  # 'c' never had an id; everyone named is tracked again

    restored = pickle.loads(pickle.dumps(tracker))
    ids = np.arange(restored.encounters.detector.n_user_ids)
    stage = restored.encounters
    assert stage.slots.of(stage.detector, restored._users, ids).tolist() == _looked_up(tracker)


def _walk_north_after_sighting(
    user: str, peer: str, sighting_ms: int, steps: int, distance_m: float
) -> UserBatch:
    """One batch: a sighting of ``peer`` at ``sighting_ms``, then ``steps`` steps of 0.7 m north, one a
    second, all after it."""
    sighting = _sighting(user, peer, sighting_ms, distance_m)
    times = sighting_ms + 1_000 * np.arange(1, steps + 1)
    return replace(
        sighting,
        step_t=times.astype(np.int64),
        step_length=np.full(steps, 0.7),
        step_azimuth=np.zeros(steps),
        step_turn=np.full(steps, math.nan),
    )


def test_an_encounter_early_in_a_long_batch_is_placed_at_its_time() -> None:
    """'a' reads 'b' 4 m away (true: a at (0, 0), b at (4, 0)), then walks 7 m north in the same batch. The
    encounter is applied after the batch's steps, so it is carried back through a's dead reckoning: a is
    not pulled toward b (applied to where a is now, a 4 m range would pull it ~2.5 m toward b, if the
    filters' 8 m apart let it be chosen at all), and its uncertainty across the pair's axis shrinks."""
    tracker = _tracker()
    outcome = tracker.apply([_walk_north_after_sighting("a", "b", T0 + 1_000, 10, 4.0)])
    assert _applied(outcome) == [("a", "b", True)]
    dead_reckoned = tracker.dead_reckoning("a")
    estimate = tracker.estimate("a")
    assert dead_reckoned is not None
    assert estimate is not None
    assert np.allclose(dead_reckoned, [0.0, 7.0], atol=1e-9)
    assert math.hypot(estimate.x, estimate.y - 7.0) < 0.5
    alone = _tracker()
    alone.apply([_walk_north_after_sighting("a", "nobody", T0 + 1_000, 10, 4.0)])
    unmeasured = alone.estimate("a")
    assert unmeasured is not None
    assert estimate.cov[0] < 0.9 * unmeasured.cov[0]  # x, the pair's axis then, is measured


def test_an_encounter_older_than_the_trail_is_not_applied() -> None:
    """A batch of 40 s whose sighting is at its start, 'a' walking 20 steps north and 20 back: a's steps kept
    reach back 30 s, so the reading's time cannot be placed. It is detected, not applied (where a is now, the
    filters' 4 m apart would have let it be chosen), and b's filter is untouched."""
    tracker = _tracker()
    before = tracker.estimate("b")
    there_and_back = _walk_north_after_sighting("a", "b", T0 + 1_000, 40, 4.0)
    there_and_back = replace(there_and_back, step_azimuth=np.repeat([0.0, math.pi], 20))
    outcome = tracker.apply([there_and_back])
    dead_reckoned = tracker.dead_reckoning("a")
    assert dead_reckoned is not None
    assert np.allclose(dead_reckoned, [0.0, 0.0], atol=1e-9)
    assert outcome.detections == 1
    assert outcome.encounters == []
    assert tracker.estimate("b") == before


def test_narrowing_the_readings_before_carrying_them_chooses_as_carrying_all(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``choose_readings`` carries only the readings the selector could choose; a reference that carries (or,
    for a lagging phone, extrapolates) every reading and lets the selector (a copy, with the same cooldowns)
    choose among them all picks the same readings with the same offsets, call after call of a busy building
    whose phones post in three calls a second."""
    import copy

    from slam_core.encounters.selection import pair_keys
    from slam_core.filter.dense_ids import unique_ints_inverse
    from slam_core.tracking.carry import carried_since

    calls: list[int] = []
    narrowed = encounter_stage.choose_readings

    def checked(means_of, detector, selector, found, slot_a, slot_b, carrier):  # type: ignore[no-untyped-def]
        reference = copy.deepcopy(selector)
        got, offset, carry_var, places = narrowed(
            means_of, detector, selector, found, slot_a, slot_b, carrier
        )
        users, columns = carrier.users, carrier.columns
        n = len(found)
        ids, who = unique_ints_inverse(np.concatenate([found.user_a, found.user_b]))
        tracks = [users[detector.user_name(i)] for i in ids.tolist()]
        t2 = np.concatenate([found.t_ms, found.t_ms])
        own_slots = np.array([u.slot for u in tracks], dtype=np.int64)[who]  # the tracks' own last events
        last = np.array([u.last_t_ms for u in tracks], dtype=np.int64)[who]
        shift, walked, placeable = carried_since(carrier.trails, own_slots, last, t2)
        # each user's guessed walk beyond its phone's last report, at its own track's velocity (all walk)
        heard_until = columns.heard_t_ms[np.concatenate([slot_a, slot_b])]
        velocity = np.array([carrier.trails.recent_velocity(u.slot) for u in tracks])[who]
        ahead = velocity * np.maximum(t2 - heard_until, 0)[:, None]
        guess_var = 0.25 * np.sum(ahead**2, axis=1)
        heard = t2 - heard_until <= 5_000
        ok = np.flatnonzero(placeable[:n] & placeable[n:] & heard[:n] & heard[n:])
        slots, index = unique_ints_inverse(np.concatenate([slot_a, slot_b]))
        means = means_of(slots)
        placed = (shift - ahead)[:n] - (shift - ahead)[n:]
        delta = means[index[:n]] - means[index[n:]] - placed
        predicted = np.hypot(delta[ok, 0], delta[ok, 1])
        sigma = np.sqrt(np.array([detector.range_model(int(m)).variance_at_distance(np.array([d]))[0]
                                  for m, d in zip(found.model[ok], predicted, strict=True)]))  # fmt: skip
        keys = pair_keys(found.user_a, found.user_b, found.model)
        want = ok[
            reference.choose(found.t_ms[ok], keys[ok], predicted, sigma, (found.user_a[ok], found.user_b[ok]))
        ]
        assert got.tolist() == want.tolist()
        np.testing.assert_allclose(offset, placed[want], atol=1e-12)
        then = means[index] - (shift - ahead)  # each user where it was at the reading
        np.testing.assert_allclose(places, np.hstack([then[:n], then[n:]])[want], atol=1e-9)
        variance = 0.01 * (walked[:n] ** 2 + walked[n:] ** 2) + guess_var[:n] + guess_var[n:]
        np.testing.assert_allclose(carry_var, variance[want], atol=1e-12)
        calls.append(int(got.size))
        far.append(int(np.sum(predicted > selector.params.select_range_m)))
        carried.append(float(np.abs(shift[:n][want]).sum() + np.abs(shift[n:][want]).sum()))
        guessed.append(float(np.abs(ahead[:n][want]).sum() + np.abs(ahead[n:][want]).sum()))
        return got, offset, carry_var, places

    far: list[int] = []
    carried: list[float] = []
    guessed: list[float] = []
    monkeypatch.setattr(encounter_stage, "choose_readings", checked)
    # scans before each batch's last step, and phones posting in three calls a second
    _busy_building(10**9, monkeypatch, scan_lag_ms=700, calls_per_second=3)
    assert len(calls) >= 21
    assert sum(calls) > 0
    assert sum(carried) > 0  # chosen readings were carried back through the walk since
    assert sum(guessed) > 0  # and lagging peers extrapolated
    assert sum(far) > 0  # and some readings were out of range, for the narrowing to leave out
