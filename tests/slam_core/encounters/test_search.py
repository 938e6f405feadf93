"""The compiled WiFi encounter search (``kernels.wifi_encounters`` through ``EncounterDetector.add_scans``)
against a plain-Python brute force over the same definitions: every earlier scan of another user that is
still remembered, inside the pair window, sharing one of the strongest N APs, compared by the references
``eq3_sparse`` or ``union_rms_sparse``; on random streams with delayed batches, and arrays small enough to
be compacted and grown."""

from __future__ import annotations

import math
import pickle
from dataclasses import dataclass

import numpy as np
import pytest

from slam_core.encounters.detection import EncounterDetector, ScanBatch
from slam_core.encounters.models import (
    MODEL_WIFI,
    MODEL_WIFI_FINGERPRINT,
    Calibration,
    DetectionParams,
    RangeModel,
)
from slam_core.wifi.pairs import fresh_mask
from tests.slam_core.wifi.reference import eq3_sparse, union_rms_sparse

CALIBRATION = Calibration(
    RangeModel("wifi-log", (1.0, 2.0), 0.5),
    RangeModel("bt-quadratic", (-60.0, -10.0, 0.0), 4.0),
    RangeModel("wifi-log", (2.0, 4.0), 1.0),
)
T0 = 1_700_000_000_000


@dataclass
class Scan:
    user: str
    t: int
    bssids: list[str]
    rss: np.ndarray
    last_seen: np.ndarray


def _stream(seed: int, n_calls: int = 40) -> list[list[Scan]]:
    """Calls of 0-12 scans from 8 users at 4 places (each place hears 12 of 30 APs at its own levels; a
    scan hears all or all but one with 2 dB noise), a second apart on average; one scan in five is from a
    batch delayed by 2.5-9 s; a few entries are cached re-reports (old last-seen)."""
    rng = np.random.default_rng(seed)
    places = [rng.choice(30, size=12, replace=False) for _ in range(4)]
    levels = [rng.uniform(-80.0, -40.0, 12) for _ in range(4)]
    calls = []
    now = T0
    for _ in range(n_calls):
        now += int(rng.integers(200, 1600))
        scans = []
        for _ in range(int(rng.integers(0, 13))):
            delay = int(rng.integers(2_500, 9_000)) if rng.random() < 0.2 else int(rng.integers(0, 1_500))
            t = now - delay
            place = int(rng.integers(0, 4))
            pick = rng.choice(12, size=12 if rng.random() < 0.7 else 11, replace=False)
            rss = np.round(levels[place][pick] + rng.normal(0.0, 2.0, pick.size), 1)
            seen = np.where(rng.random(pick.size) < 0.03, t - 10_000, -1).astype(np.int64)
            bssids = [f"ap{h:02d}" for h in places[place][pick]]
            scans.append(Scan(f"u{rng.integers(0, 8)}", t, bssids, rss, seen))
        calls.append(scans)
    return calls


def _brute_force(calls: list[list[Scan]], params: DetectionParams) -> list[tuple[int, str, str, float]]:
    """The definition, written out: each scan against every earlier one still remembered (the arrival-order
    horizon of ``retention_ms`` behind the newest scan time)."""
    by_fingerprint = params.wifi_model == "wifi-fingerprint"
    stored: list[tuple[str, int, dict[str, float], dict[str, float]]] = []
    head = 0
    newest = -math.inf
    out = []
    for scan in (s for call in calls for s in call):
        keep = np.flatnonzero(fresh_mask(scan.t, scan.last_seen, params.stale_ap_ms))
        if keep.size == 0:
            continue
        order = keep[np.argsort(-scan.rss[keep], kind="stable")[: params.wifi.strongest_n]]
        top = {scan.bssids[i]: float(scan.rss[i]) for i in order}
        fresh = {scan.bssids[i]: float(scan.rss[i]) for i in keep}
        newest = max(newest, scan.t)
        horizon = newest - params.retention_ms
        while head < len(stored) and stored[head][1] < horizon:
            head += 1
        for user, t, other_top, other_fresh in stored[head:]:
            if user == scan.user or abs(t - scan.t) > params.scan_pair_window_ms or t < horizon:
                continue
            if not top.keys() & other_top.keys():
                continue
            if by_fingerprint:
                feature = union_rms_sparse(fresh, other_fresh, params.fingerprint.floor_dbm)
                passing = feature < params.fingerprint.threshold_db
            else:
                feature, n = eq3_sparse(top, other_top)
                passing = n >= params.wifi.min_common and feature < params.wifi.threshold_db
            if passing:
                out.append((max(t, scan.t), scan.user, user, feature))
        stored.append((scan.user, scan.t, top, fresh))
    return out


def _compiled(
    calls: list[list[Scan]], params: DetectionParams, capacity: int, background: bool = False
) -> list[tuple[int, str, str, float]]:
    """``add_scans`` call by call; with ``background``, ``start_scans`` on a thread, collected after a
    pickle round trip of the detector of the call before (what a snapshot between calls does)."""
    detector = EncounterDetector(params, CALIBRATION, scan_capacity=capacity)
    out = []
    kind = MODEL_WIFI_FINGERPRINT if params.wifi_model == "wifi-fingerprint" else MODEL_WIFI
    for call in calls:
        if not call:
            continue
        offsets = np.cumsum([0] + [len(s.bssids) for s in call])
        args = (
            [s.user for s in call],
            np.array([s.t for s in call]),
            offsets,
            [b for s in call for b in s.bssids],
            np.concatenate([s.rss for s in call]),
            np.concatenate([s.last_seen for s in call]),
        )
        if background:
            detector = pickle.loads(pickle.dumps(detector))
            found = detector.start_scans(ScanBatch(*args), background=True).result()
        else:
            found = detector.add_scans(*args)
        assert np.all(found.model == kind)
        out += [(d.t_ms, d.user_a, d.user_b, d.feature) for d in detector.to_detections(found)]
    return out


@pytest.mark.parametrize("model", ["wifi-eq3", "wifi-fingerprint"])
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(("capacity", "background"), [(2, False), (1024, False), (2, True)])
def test_compiled_search_equals_the_brute_force(
    model: str, seed: int, capacity: int, background: bool
) -> None:
    params = DetectionParams(wifi_model=model)
    calls = _stream(seed)
    expected = _brute_force(calls, params)
    got = _compiled(calls, params, capacity, background)
    assert len(expected) > 20  # the streams do meet
    assert [g[:3] for g in got] == [e[:3] for e in expected]
    np.testing.assert_allclose([g[3] for g in got], [e[3] for e in expected], rtol=1e-12, atol=1e-12)


def test_delayed_batches_meet_their_partners_and_old_scans_are_forgotten() -> None:
    detector = EncounterDetector(DetectionParams(), CALIBRATION)
    here = (["aa", "bb", "cc"], np.array([-50.0, -60.0, -70.0]), np.full(3, -1, dtype=np.int64))

    def scan(user: str, t: int) -> list[tuple[str, str]]:
        return [(d.user_a, d.user_b) for d in detector.add_scan(user, t, *here)]

    assert scan("a", T0) == []
    for k in range(3, 9):  # others walk on, 3-8 s later: "a" falls behind the index's 2 s bound
        assert scan(f"x{k}", T0 + 1_000 * k) == ([] if k == 3 else [(f"x{k}", f"x{k - 1}")])
    assert scan("b", T0 + 300) == [("b", "a")]  # 7.7 s late: its walk of the index reaches "a"
    assert scan("c", T0 + 600) == [("c", "a"), ("c", "b")]  # "b" is found in the list of late scans
    assert detector.n_indexed_scans == 9
    assert scan("d", T0 + 30_000) == []
    assert detector.n_indexed_scans == 1  # everything else fell behind the 10 s retention


def test_scans_compared_on_a_thread_hold_the_detector_until_collected() -> None:
    detector = EncounterDetector(DetectionParams(), CALIBRATION)
    here = (["aa", "bb", "cc"], np.array([-50.0, -60.0, -70.0]), np.full(3, -1, dtype=np.int64))
    assert detector.add_scan("a", T0, *here) == []
    users, t, offsets = ["b", "c"], np.array([T0 + 100, T0 + 200]), np.array([0, 3, 6])
    args = (users, t, offsets, here[0] * 2, np.tile(here[1], 2), np.tile(here[2], 2))
    pending = detector.start_scans(ScanBatch(*args), background=True)
    with pytest.raises(RuntimeError, match="not been collected"):
        detector.start_scans(ScanBatch(*args), background=False)
    with pytest.raises(RuntimeError, match="cannot pickle"):
        pickle.dumps(detector)
    found = detector.to_detections(pending.result())
    assert [(d.user_a, d.user_b) for d in found] == [("b", "a"), ("c", "a"), ("c", "b")]
    assert detector.n_indexed_scans == 3
    restored = pickle.loads(pickle.dumps(detector))  # free again, and a snapshot keeps no thread
    assert restored.add_scan("d", T0 + 300, *here) != []


def test_a_failed_comparison_raises_in_the_caller_and_frees_the_detector(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    detector = EncounterDetector(DetectionParams(), CALIBRATION)
    here = (["aa", "bb", "cc"], np.array([-50.0, -60.0, -70.0]), np.full(3, -1, dtype=np.int64))

    def broken(*_: object) -> None:
        raise MemoryError("no room for the scans")

    monkeypatch.setattr(detector._store, "add", broken)
    pending = detector.start_scans(ScanBatch(["a"], np.array([T0]), np.array([0, 3]), *here), background=True)
    with pytest.raises(MemoryError, match="no room"):
        pending.result()
    monkeypatch.undo()
    assert detector.add_scan("b", T0 + 100, *here) == []  # the detector is usable again
