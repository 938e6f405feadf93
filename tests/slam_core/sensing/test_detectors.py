"""Building-anchor detectors: turns, radio visits reported at their peak, and their bookkeeping."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from slam_core.sensing.detectors import (
    DetectorParams,
    DetectorState,
    detect_radio,
    detect_turns,
    merge_events,
    step_headings,
)

P = DetectorParams(turns=True)
NO_SCANS = (np.zeros(0, np.int64), np.zeros(1, np.int64), (), np.zeros(0), np.zeros(0, np.int64))


def _beacons(
    state: DetectorState, rows: list[tuple[int, str, float]], params: DetectorParams = P
) -> list[tuple[int, int, str, int]]:
    t = np.array([r[0] for r in rows], dtype=np.int64)
    return detect_radio(
        state, params, *NO_SCANS, t, tuple(r[1] for r in rows), np.array([r[2] for r in rows])
    )


def test_a_right_angle_turn_fires_once() -> None:
    headings = np.r_[np.zeros(10), np.full(10, math.pi / 2)]
    t = np.arange(20) * 600
    fired = detect_turns(DetectorState(), P, t, headings)
    assert fired == [int(t[10])]


def test_turn_refractory_and_gentle_curves() -> None:
    state = DetectorState()
    zigzag = np.tile([0.0, 0.0, math.radians(80), math.radians(80)], 5)
    fired = detect_turns(state, P, np.arange(zigzag.size) * 600, zigzag)
    assert all(b - a > P.turn_refractory_steps * 600 for a, b in itertools.pairwise(fired))
    gentle = np.cumsum(np.full(30, math.radians(10)))  # 10 deg a step: 30 deg over the 3-step window
    assert detect_turns(DetectorState(), P, np.arange(30) * 600, gentle) == []
    assert detect_turns(DetectorState(), P, np.arange(3), np.full(3, np.nan)) == []


def test_turns_seen_across_batches_fire_once() -> None:
    headings = np.r_[np.zeros(10), np.full(10, math.pi / 2)]
    t = np.arange(20) * 600
    state = DetectorState()
    fired = detect_turns(state, P, t[:11], headings[:11]) + detect_turns(state, P, t[11:], headings[11:])
    assert fired == detect_turns(DetectorState(), P, t, headings)


def test_step_headings_from_azimuths_or_turns() -> None:
    state = DetectorState(headings=[1.0])
    out = step_headings(state, np.array([0.0, np.nan, np.nan]), np.array([np.nan, 0.5, np.nan]))
    np.testing.assert_allclose(out, [math.pi / 2, math.pi / 2 + 0.5, math.pi / 2 + 0.5])
    assert step_headings(DetectorState(), np.array([np.nan]), np.array([0.3]))[0] == pytest.approx(0.3)


def test_a_beacon_visit_is_reported_once_at_its_peak() -> None:
    state = DetectorState()
    out = _beacons(state, [(1000, "AA:00", -70.0), (2000, "AA:00", -62.0), (3000, "AA:00", -55.0)])
    assert out == []  # still rising
    out = _beacons(state, [(4000, "AA:00", -57.0), (5000, "AA:00", -60.0), (6000, "AA:00", -58.0)])
    assert out == [(5000, P.beacon_type, "beacon:aa:00", 3000)]  # 3 dB under the peak, once
    assert _beacons(state, [(7000, "AA:00", -50.0)]) == []  # same visit: not again
    later = 7000 + P.visit_gap_ms + 1
    assert _beacons(state, [(later, "AA:00", -60.0), (later + 1000, "AA:00", -64.0)]) == [
        (later + 1000, P.beacon_type, "beacon:aa:00", later)
    ]


def test_a_visit_that_goes_quiet_is_reported() -> None:
    state = DetectorState()
    assert _beacons(state, [(1000, "AA:00", -60.0), (2000, "BB:00", -90.0)]) == []
    out = _beacons(state, [(1000 + P.quiet_ms, "BB:00", -90.0)])
    assert out == [(1000 + P.quiet_ms, P.beacon_type, "beacon:aa:00", 1000)]
    _beacons(state, [(1000 + P.visit_gap_ms + 1, "BB:00", -90.0)])
    assert "beacon:aa:00" not in state.visits  # memory stays bounded


def test_wifi_visits_ignore_cached_entries_and_count_one_place_once() -> None:
    state = DetectorState()

    def scan(t: int, rss: list[float], last_seen: list[int]) -> list[tuple[int, int, str, int]]:
        bssids = ("0a:00:00:00:00:01", "0a:00:00:00:00:02", "0b:00:00:00:00:09")
        return detect_radio(
            state, P, np.array([t]), np.array([0, 3]), bssids, np.array(rss), np.array(last_seen),
            np.zeros(0, np.int64), (), np.zeros(0),
        )  # fmt: skip

    t0 = 1_700_000_000_000
    assert scan(t0, [-40, -41, -30], [t0, t0, t0 - P.stale_ap_ms - 1]) == []
    out = scan(t0 + 2000, [-48, -47, -30], [t0 + 2000, t0 + 2000, t0 - P.stale_ap_ms])
    assert len(out) == 1  # two BSSIDs of one access point peaked together: one report
    assert out[0][1] == P.wifi_type
    assert out[0][3] == t0
    assert all("0b:00" not in s for s in state.visits)  # the cached entry never opened a visit


def test_detectors_can_be_switched_off() -> None:
    off = DetectorParams(beacons=False, wifi=False)
    state = DetectorState()
    assert _beacons(state, [(1000, "AA:00", -50.0), (2000, "AA:00", -70.0)], off) == []
    assert state.visits == {}


def test_merge_events_orders_by_report_time() -> None:
    events = merge_events([5000], [(3000, 6, "beacon:x", 1000)], 3)
    assert events.t_ms.tolist() == [3000, 5000]
    assert events.type_index.tolist() == [6, 3]
    assert events.signature == ("beacon:x", "")
    assert events.observed_t_ms.tolist() == [1000, 5000]
    assert np.isnan(events.rise_m).all()
    assert merge_events([], [], 3).t_ms.size == 0
    # a change of floor carries its rise; the others none
    up = merge_events([5000], [], 3, [(4000, 1, "", 2500, 4.4)])
    assert up.type_index.tolist() == [1, 3]
    assert up.rise_m[0] == 4.4
    assert np.isnan(up.rise_m[1])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"turn_deg": 0.0}, "turn_deg"),
        ({"turn_window_steps": 0}, "turn_window_steps"),
        ({"visit_gap_ms": 0}, "visit_gap_ms"),
        ({"stale_ap_ms": -1}, "stale_ap_ms"),
    ],
)
def test_bad_parameters(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        DetectorParams(**kwargs)  # type: ignore[arg-type]
