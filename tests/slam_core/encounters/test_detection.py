"""Online WiFi encounter detection with the paper's Eq. 3 and with our union-fingerprint model."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from slam_core.encounters.detection import EncounterDetector, ScanBatch, _PreparedScans
from slam_core.encounters.models import (
    ENCOUNTER_MODELS,
    MODEL_WIFI,
    MODEL_WIFI_FINGERPRINT,
    Calibration,
    DetectionParams,
    RangeModel,
    WifiFingerprintParams,
    encounter_model,
)
from slam_core.wifi.pairs import fresh_mask

BT = RangeModel("bt-quadratic", (-60.0, -10.0, 0.0), 4.0)
EQ3 = RangeModel("wifi-log", (1.0, 2.0), 0.5)
FINGERPRINT = RangeModel("wifi-log", (2.0, 4.0), 1.0)
T0 = 1_700_000_000_000
BSSIDS = [f"0a:00:00:00:00:{i:02x}" for i in range(12)]


def _scan(detector: EncounterDetector, user: str, t: int, rss: list[float]) -> list:  # type: ignore[type-arg]
    heard = [(b, r) for b, r in zip(BSSIDS, rss, strict=True) if math.isfinite(r)]
    return detector.add_scan(
        user,
        t,
        [b for b, _ in heard],
        np.array([r for _, r in heard]),
        np.full(len(heard), -1, dtype=np.int64),
    )


@pytest.mark.parametrize(
    ("model", "kind"), [("wifi-eq3", MODEL_WIFI), ("wifi-fingerprint", MODEL_WIFI_FINGERPRINT)]
)
def test_two_phones_in_the_same_place_meet_and_far_ones_do_not(model: str, kind: int) -> None:
    detector = EncounterDetector(DetectionParams(wifi_model=model), Calibration(EQ3, BT, FINGERPRINT))
    here = [-45.0, -50.0, -55.0, -60.0, -65.0, -70.0, -75.0, -80.0, math.nan, math.nan, math.nan, math.nan]
    there = [math.nan, math.nan, math.nan, math.nan, -80.0, -75.0, -70.0, -65.0, -60.0, -55.0, -50.0, -45.0]
    assert _scan(detector, "a", T0, here) == []
    met = _scan(detector, "b", T0 + 300, [r + 1.0 if math.isfinite(r) else r for r in here])
    assert [(d.user_a, d.user_b, d.model) for d in met] == [("b", "a", kind)]
    assert detector.ranged(met)[0].distance_m < 3.0
    assert _scan(detector, "c", T0 + 20_000, there) == []
    # "d" hears "c"'s strongest APs just as "c" does, and four loud APs that "c" does not hear at all:
    # Eq. 3 only compares the common strongest APs and passes; the union of APs tells them apart
    mixed = _scan(detector, "d", T0 + 20_300, here[:4] + there[4:])
    assert len(mixed) == (1 if model == "wifi-eq3" else 0)


def test_the_fingerprint_model_needs_its_calibration_and_a_known_name() -> None:
    with pytest.raises(ValueError, match="calibrate"):
        EncounterDetector(DetectionParams(wifi_model="wifi-fingerprint"), Calibration(EQ3, BT))
    with pytest.raises(ValueError, match="unknown WiFi encounter model"):
        DetectionParams(wifi_model="wifi-magic")
    assert isinstance(encounter_model("wifi-fingerprint"), WifiFingerprintParams)
    assert set(ENCOUNTER_MODELS) == {"wifi-eq3", "wifi-fingerprint", "bluetooth"}
    with pytest.raises(ValueError, match="valid: wifi-eq3, wifi-fingerprint, bluetooth"):
        encounter_model("lte")


def test_calibration_round_trips_with_and_without_the_fingerprint_model() -> None:
    with_fp = Calibration(EQ3, BT, FINGERPRINT)
    assert Calibration.from_dict(with_fp.to_dict()) == with_fp
    without = Calibration(EQ3, BT)
    assert "wifi_fingerprint" not in without.to_dict()
    assert Calibration.from_dict(without.to_dict()) == without
    broken = {
        **with_fp.to_dict(),
        "wifi_fingerprint": {"kind": "bt-quadratic", "coefficients": [1.0], "sigma": 1},
    }
    with pytest.raises(ValueError, match="wifi_fingerprint"):
        Calibration.from_dict(broken)


def test_bluetooth_pairs_not_heard_within_the_retention_are_forgotten() -> None:
    """A pair's sightings average over one sighting period; pairs silent for ``retention_ms`` are dropped
    as time advances (a long-running building holds only its recent pairs), and a pair heard again starts
    its average afresh with the same result."""
    params = DetectionParams()
    detector = EncounterDetector(params, Calibration(EQ3, BT))
    for k in range(50):  # 50 pairs, each heard once, 100 ms apart
        detector.add_sightings([f"u{k}"], [f"v{k}"], np.array([T0 + 100 * k]), np.array([-70.0]))
    assert len(detector._bt) == 50
    later = T0 + 100 * 30 + params.retention_ms  # pairs heard before T0 + 3,000 ms are past the retention
    found = detector.add_sightings(
        ["u0", "w"], ["v0", "x"], np.array([later, later]), np.array([-75.0, -95.0])
    )
    assert len(detector._bt) == 50 - 30 + 2  # u0..u29 went; u0-v0 came back and w-x joined
    assert ("u29", "v29") not in detector.bluetooth_pairs()
    assert ("u30", "v30") in detector.bluetooth_pairs()
    # u0-v0 is detected on its new reading alone (-75 dBm, above the cut-off); w-x at -95 dBm is not
    assert found.feature.tolist() == [-75.0]


def test_bluetooth_pairs_keep_their_order_through_a_snapshot() -> None:
    """Pairs run from the least recently heard (a pair heard again moves to the end); a snapshot stores the
    pairs' arrays (no object per pair or sighting), and the restored detector forgets the same pairs as the
    original."""
    params = DetectionParams()
    detector = EncounterDetector(params, Calibration(EQ3, BT))
    for k in range(20):
        detector.add_sightings([f"u{k}"], [f"v{k}"], np.array([T0 + 100 * k]), np.array([-70.0]))
    detector.add_sightings(["v3"], ["u3"], np.array([T0 + 2_500]), np.array([-72.0]))  # heard again
    order = detector.bluetooth_pairs()
    assert order == [(f"u{k}", f"v{k}") for k in range(20) if k != 3] + [("u3", "v3")]
    state = detector.__getstate__()["_bt"].__dict__
    assert all(isinstance(value, np.ndarray) for value in state.values())
    restored = pickle.loads(pickle.dumps(detector))
    assert restored.bluetooth_pairs() == order
    later = T0 + 100 * 10 + params.retention_ms  # u0..u9 (but u3) are past the retention
    for d in (detector, restored):
        d.add_sightings(["a"], ["b"], np.array([later]), np.array([-95.0]))
    assert restored.bluetooth_pairs() == detector.bluetooth_pairs() == [*order[9:], ("a", "b")]


class _TupleHistories:
    """The Bluetooth smoothing as it was first written (tuples of (t, rss) per pair of names): the oracle
    for the packed histories."""

    def __init__(self, params: DetectionParams) -> None:
        self.params = params
        self.bt: dict[tuple[str, str], tuple[tuple[int, float], ...]] = {}
        self.newest = 0

    def add(self, receiver: str, sender: str, t: int, rss: float) -> float | None:
        if t > self.newest:
            self.newest = t
            horizon = t - self.params.retention_ms
            while self.bt:  # from the least recently heard (the dict's order), as the detector does
                oldest = next(iter(self.bt))
                if self.bt[oldest][-1][0] >= horizon:
                    break
                del self.bt[oldest]
        pair = (min(receiver, sender), max(receiver, sender))
        history = (*self.bt.pop(pair, ()), (t, rss))
        start = 0
        while start < len(history) and t - history[start][0] >= self.params.bt_smoothing_ms:
            start += 1
        self.bt[pair] = history[start:]
        smoothed = sum(r for _, r in self.bt[pair]) / len(self.bt[pair])
        return smoothed if smoothed >= self.params.bluetooth.cutoff_dbm else None


@pytest.mark.parametrize(("seed", "phones", "calls"), [(0, 12, 60), (1, 12, 60), (2, 80, 150), (3, 300, 80)])
def test_bluetooth_smoothing_matches_the_tuple_oracle(seed: int, phones: int, calls: int) -> None:
    """Random sightings among the phones (times mostly increasing, some late, some repeated; RSS around the
    cut-off): the same detections with bit-identical averages, and the same pairs kept in the same order,
    as the oracle; with many phones the pair table and the sightings' pool grow and are rebuilt with
    forgotten pairs in them, and a snapshot taken on the way goes on alike."""
    rng = np.random.default_rng(seed)
    params = DetectionParams()
    detector = EncounterDetector(params, Calibration(EQ3, BT))
    oracle = _TupleHistories(params)
    names = [f"p{k}" for k in range(phones)]
    t = T0
    for call in range(calls):
        if call == calls // 2:
            detector = pickle.loads(pickle.dumps(detector))
        n = int(rng.integers(1, 30 if phones < 50 else 400))
        t += int(rng.integers(0, 1_500))
        times = t + rng.integers(-1_200, 400, n)  # a batch's sightings, some before the newest seen
        rss = rng.normal(-88.0, 6.0, n)
        receivers = [names[i] for i in rng.integers(0, phones, n)]
        senders = [names[i] for i in rng.integers(0, phones, n)]
        found = detector.add_sightings(receivers, senders, times, rss)
        expected = []
        for rx, tx, ti, ri in zip(receivers, senders, times.tolist(), rss.tolist(), strict=True):
            if rx == tx:
                continue
            smoothed = oracle.add(rx, tx, ti, ri)
            if smoothed is not None:
                expected.append((ti, rx, tx, smoothed))
        got = [
            (ti, detector.user_name(a), detector.user_name(b), f)
            for ti, a, b, f in zip(
                found.t_ms.tolist(),
                found.user_a.tolist(),
                found.user_b.tolist(),
                found.feature.tolist(),
                strict=True,
            )
        ]
        assert got == expected
        assert [tuple(sorted(p)) for p in detector.bluetooth_pairs()] == list(oracle.bt)
        assert len(detector._bt) == len(oracle.bt)


def test_bluetooth_smoothing_needs_a_window() -> None:
    with pytest.raises(ValueError, match="bt_smoothing_ms"):
        DetectionParams(bt_smoothing_ms=0)


def _prepared_scan_by_scan(detector: EncounterDetector, scans: ScanBatch) -> _PreparedScans | None:
    """The scans' preparation as it was first written, one scan at a time: the oracle for the call-wide
    masks and sorts of ``EncounterDetector._prepared``."""
    p = detector.params
    by_fingerprint = p.wifi_model == "wifi-fingerprint"
    n_top = p.wifi.strongest_n
    users, t_ms, offsets, bssids = scans.users, scans.t_ms, scans.offsets, scans.bssids
    rss, last_seen_ms = scans.rss, scans.last_seen_ms
    kept_t, kept_user, tops, top_rss = [], [], [], []
    fresh_ap: list[int] = []
    fresh_rss: list[float] = []
    fresh_offsets = [0]
    for c in range(len(users)):
        lo, hi = int(offsets[c]), int(offsets[c + 1])
        t = int(t_ms[c])
        keep = lo + np.flatnonzero(fresh_mask(t, last_seen_ms[lo:hi], p.stale_ap_ms))
        if keep.size == 0:
            continue
        order = keep[np.argsort(-rss[keep], kind="stable")[:n_top]]
        top = {detector._intern(bssids[i]): float(rss[i]) for i in order.tolist()}
        kept_t.append(t)
        kept_user.append(detector.user_id(users[c]))
        row = np.full(n_top, -1, dtype=np.int64)
        row[: len(top)] = list(top)
        tops.append(row)
        values = np.zeros(n_top)
        values[: len(top)] = list(top.values())
        top_rss.append(values)
        if by_fingerprint:
            fresh = {detector._intern(bssids[i]): float(rss[i]) for i in keep.tolist()}
            fresh_ap += fresh
            fresh_rss += fresh.values()
        fresh_offsets.append(len(fresh_ap))
    if not kept_t:
        return None
    return _PreparedScans(
        np.array(kept_t, dtype=np.int64),
        np.array(kept_user, dtype=np.int64),
        np.array(tops),
        np.array(top_rss),
        np.array(fresh_offsets, dtype=np.int64),
        np.array(fresh_ap, dtype=np.int64),
        np.array(fresh_rss, dtype=np.float64),
        len(detector._ap_ids),
    )


@pytest.mark.parametrize("model", ["wifi-eq3", "wifi-fingerprint"])
@pytest.mark.parametrize("seed", range(3))
def test_a_calls_scans_are_prepared_as_one_scan_at_a_time(model: str, seed: int) -> None:
    """Calls of random scans (some empty or all stale, BSSIDs repeated within a scan in either case, RSS
    ties, more entries than the strongest N): the same kept scans, strongest entries, fresh entries, and
    BSSIDs and users interned in the same order, as the scan-by-scan oracle."""
    rng = np.random.default_rng(seed)
    calibration = Calibration(EQ3, BT, FINGERPRINT)
    detector = EncounterDetector(DetectionParams(wifi_model=model), calibration)
    oracle = EncounterDetector(DetectionParams(wifi_model=model), calibration)
    pool = [f"0a:00:00:00:{i // 256:02x}:{i % 256:02x}" for i in range(300)]
    for call in range(25):
        n = int(rng.integers(1, 12))
        counts = rng.integers(0, 30, n)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        total = int(offsets[-1])
        t = T0 + 1_000 * call + np.sort(rng.integers(0, 1_000, n))
        bssids = [pool[i] for i in rng.integers(0, 40 + 10 * call, total)]
        if total > 3:
            bssids[1] = bssids[0].upper()  # the same AP, spelled otherwise
        rss = np.round(rng.normal(-70.0, 8.0, total))  # whole dB: ties
        scan_t = np.repeat(t, counts)
        last_seen = np.where(rng.random(total) < 0.3, scan_t - rng.integers(0, 20_000, total), -1)
        users = [f"u{i}" for i in rng.integers(0, 15, n)]
        scans = ScanBatch(users, t, offsets, bssids, rss, last_seen)
        got, want = detector._prepared(scans), _prepared_scan_by_scan(oracle, scans)
        if want is None:
            assert got is None
            continue
        assert got is not None
        for name in ("t_ms", "user", "top_ap", "top_rss", "fresh_offsets", "fresh_ap", "fresh_rss"):
            assert np.array_equal(getattr(got, name), getattr(want, name)), (call, name)
            assert getattr(got, name).dtype == getattr(want, name).dtype, name
        assert got.n_aps == want.n_aps
        assert detector._ap_ids == oracle._ap_ids
        assert list(detector._ap_ids) == list(oracle._ap_ids)
        assert detector._user_names == oracle._user_names
    # a call's entries may start past the arrays' first (the offsets say where)
    shifted = ScanBatch(["a"], np.array([T0]), np.array([2, 5]), ["x", "y", *BSSIDS[:3]],
                        np.array([0.0, 0.0, -60.0, -50.0, -70.0]), np.full(5, -1))  # fmt: skip
    got, want = detector._prepared(shifted), _prepared_scan_by_scan(oracle, shifted)
    assert got is not None
    assert want is not None
    assert np.array_equal(got.top_ap, want.top_ap)
    assert np.array_equal(got.top_rss, want.top_rss)
