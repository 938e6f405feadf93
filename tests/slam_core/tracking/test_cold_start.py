"""A phone with no start fix is placed by the crowd's fingerprint map: spread over its first scan's candidate
places, weighed by each later scan's, reported once confident."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.crowd.fingerprints import FingerprintParams
from slam_core.encounters.models import Calibration, RangeModel
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.filter.floor_plan import PlanIndex
from slam_core.filter.params import FilterParams
from slam_core.tracking.params import ColdStartParams
from slam_core.tracking.tracker import BuildingTracker, TrackerParams, UserBatch

T0 = 1_700_000_000_000
CAL = Calibration(RangeModel("wifi-log", (0.0, 2.0), 3.0), RangeModel("bt", (-60.0, -9.0, 0.0), 2.8))
APS = [(x, y) for x in np.linspace(0, 80, 9) for y in (-4.0, 4.0)]
NAMES = [f"0a:00:00:00:01:{i:02x}" for i in range(len(APS))]


def _rss(xy: np.ndarray, rng: np.random.Generator) -> tuple[list[str], np.ndarray]:
    """A scan at ``xy`` of APs along an 80 m corridor: log-distance, 2 dB noise, heard above -90 dBm."""
    d = np.hypot(*(np.asarray(APS) - xy).T)
    rss = -40.0 - 25.0 * np.log10(np.maximum(d, 1.0)) + rng.normal(0, 2.0, d.size)
    heard = rss > -90.0
    return [n for n, h in zip(NAMES, heard, strict=True) if h], rss[heard]


def _surveyed(tracker: BuildingTracker, rng: np.random.Generator) -> None:
    """A radio map of the corridor: a scan every 2 m, as a signal-map build would leave."""
    xs = np.arange(0.0, 80.0, 2.0)
    scans = [_rss(np.array([x, 0.0]), rng) for x in xs]
    tracker.load_radio_map(
        "survey",
        np.column_stack([xs, np.zeros_like(xs)]),
        [s[0] for s in scans],
        [s[1] for s in scans],
        np.full(xs.size, T0 - 3_600_000, dtype=np.int64),
    )


def _second(user: str, k: int, x: float, rng: np.random.Generator) -> UserBatch:
    """One second of a walk east at 1.4 m/s: two steps and a scan where the user is."""
    return walking_second(user, k, *_rss(np.array([x, 0.0]), rng))


def walking_second(user: str, k: int, names: list[str], rss: np.ndarray) -> UserBatch:
    """Second ``k`` of a walk east: two steps of 0.7 m and the scan ``names``, ``rss``."""
    t = T0 + 1000 * k
    return UserBatch(
        user=user,
        step_t=np.array([t + 250, t + 750], dtype=np.int64),
        step_length=np.array([0.7, 0.7]),
        step_azimuth=np.array([math.pi / 2, math.pi / 2]),
        step_turn=np.full(2, np.nan),
        scan_t=np.array([t + 500], dtype=np.int64),
        scan_offsets=np.array([0, len(names)], dtype=np.int64),
        scan_bssid=tuple(names),
        scan_rss=rss,
        scan_last_seen=np.full(len(names), -1, dtype=np.int64),
    )


def _params(enabled: bool = True, confident_sigma_m: float = 5.0) -> TrackerParams:
    return TrackerParams(
        fingerprints=FingerprintParams(enabled=True, min_references=10),
        cold_start=ColdStartParams(enabled=enabled, confident_sigma_m=confident_sigma_m),
    )


def test_a_phone_without_a_fix_is_placed_by_the_crowds_map() -> None:
    rng = np.random.default_rng(3)
    tracker = BuildingTracker(_params(confident_sigma_m=2.5), CAL, seed=1)  # placed once within 2.5 m
    _surveyed(tracker, rng)
    statuses, x = [], 10.0
    for k in range(40):
        x += 1.4
        outcome = tracker.apply([_second("walker", k, x, rng)])
        report = outcome.reports["walker"]
        statuses.append(report.status)
        if report.status == "placing":
            assert "walker" not in outcome.estimates  # nothing reported until placed
            assert not tracker.is_placed("walker")
    assert statuses[0] == "placing"  # started at its first scan, not awaiting a fix
    assert "tracking" in statuses
    placed_at = statuses.index("tracking")
    assert set(statuses[placed_at:]) == {"tracking"}  # placed for good
    row = tracker.estimate("walker")
    assert row is not None
    assert abs(row.x - x) < 5.0
    assert abs(row.y) < 5.0


def test_without_cold_starts_or_a_map_a_phone_waits_for_a_fix() -> None:
    rng = np.random.default_rng(4)
    off = BuildingTracker(_params(enabled=False), CAL, seed=1)
    _surveyed(off, rng)
    assert off.apply([_second("w", 0, 10.0, rng)]).reports["w"].status == "awaiting_fix"
    empty = BuildingTracker(_params(), CAL, seed=1)  # no map yet
    report = empty.apply([_second("w", 0, 10.0, rng)]).reports["w"]
    assert report.status == "awaiting_fix"
    assert report.steps_dropped == 2


def test_particles_start_among_the_candidates_and_off_the_plan_weigh_less() -> None:
    engine = DynamicSlam(FilterParams(n_particles=200), seed=2)
    engine.set_floor_plan(
        0, PlanIndex.build(np.zeros((0, 4)), [np.array([[0, -5], [100, -5], [100, 5], [0, 5.0]])])
    )
    centres = np.array([[10.0, 0.0], [60.0, 0.0], [60.0, 30.0]])  # the last off the walkable corridor
    slot = engine.add_user_among(centres, np.array([1.0, 1.0, 2.0]), 2.0)
    s = engine.state
    xy = np.column_stack([s.x[slot], s.y[slot]])
    nearest = np.argmin(np.linalg.norm(xy[:, None] - centres[None], axis=2), axis=1)
    assert set(np.unique(nearest)) == {0, 1, 2}
    assert abs(np.mean(nearest == 2) - 0.5) < 0.12  # drawn by weight
    w = np.exp(s.logw[slot])
    assert math.isclose(w.sum(), 1.0)
    off = ~engine.floor_plans[0].walkable(xy)
    assert off[nearest == 2].all()
    assert w[off].max() < w[~off].min()  # off the plan: weighed down
    # the same admission draws the same particles (randomness from the filter's seed)
    again = DynamicSlam(FilterParams(n_particles=200), seed=2)
    again.set_floor_plan(0, engine.floor_plans[0])
    twin = again.add_user_among(centres, np.array([1.0, 1.0, 2.0]), 2.0)
    np.testing.assert_array_equal(again.state.x[twin], s.x[slot])
    # a scan that matches one place takes the cloud there
    engine.observe_places(slot, np.array([[60.0, 0.0]]), np.array([1.0]), 4.0, 0.3, 50.0)
    w = np.exp(engine.state.logw[slot])
    mean = np.array([w @ engine.state.x[slot], w @ engine.state.y[slot]])
    assert np.linalg.norm(mean - [60.0, 0.0]) < 6.0
    assert np.all(np.isfinite(engine.state.logw[slot]))


@pytest.mark.parametrize(
    ("centres", "weights", "sigma"),
    [
        (np.zeros((0, 2)), np.zeros(0), 1.0),
        (np.array([[0.0, np.nan]]), np.ones(1), 1.0),
        (np.zeros((1, 2)), np.zeros(1), 1.0),
        (np.zeros((1, 2)), np.ones(1), -1.0),
    ],
)
def test_bad_candidates_are_refused_and_change_nothing(
    centres: np.ndarray, weights: np.ndarray, sigma: float
) -> None:
    engine = DynamicSlam(FilterParams(n_particles=8), seed=0)
    with pytest.raises(ValueError, match=r"candidate|weights|sigma"):
        engine.add_user_among(centres, weights, sigma)
    assert engine.active_users.size == 0
