"""Online encounter detection across one building's users (DynamicSLAM Section 4.1.2), as scans and
sightings arrive.

WiFi: each scan is compared, by Eq. 3, with the other users' scans within ``scan_pair_window_ms``. Eq. 3
only compares APs common to both scans' strongest N, so a scan can only pass against scans sharing one of
its strongest N APs: an inverted index from those APs to recent scans finds every candidate, and the cost
of a scan does not grow with the number of users in the building.

Bluetooth: a phone's sighting of another phone's advertised id, averaged per pair (both directions) over
``bt_smoothing_ms`` (one sighting period), is an encounter above the -90 dBm cut-off.

Every detection is reported; which ones become human anchors is chosen by the tracker from the filters'
estimates (``slam_core.encounter_selection``), as in the simulated evaluation, and only those are ranged
(calibrated range and R, ``ranged``).
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from collections import defaultdict, deque
from dataclasses import dataclass, field

import numpy as np

from slam_core.encounters import (
    BluetoothParams,
    Calibration,
    RangeModel,
    WifiEq3Params,
    WifiFingerprintParams,
)
from slam_core.wifi_pairs import STALE_AP_MS, fresh_mask

MODEL_WIFI = 0
MODEL_BLUETOOTH = 1
MODEL_WIFI_FINGERPRINT = 2
WIFI_MODELS = ("wifi-eq3", "wifi-fingerprint")


@dataclass(frozen=True)
class DetectionParams:
    wifi: WifiEq3Params = field(default_factory=WifiEq3Params)
    bluetooth: BluetoothParams = field(default_factory=BluetoothParams)
    scan_pair_window_ms: int = 1_000
    bt_smoothing_ms: int = 1_000
    """One sighting period: a longer window blurs the range of pairs walking towards each other."""
    stale_ap_ms: int = STALE_AP_MS
    """Beyond the paper: scans re-report cached APs (on real phones 50-60 % of entries are older than 3 s);
    entries whose last-seen time is more than this before the scan are dropped before Eq. 3."""
    retention_ms: int = 10_000
    """Scans and sightings older than this (behind the newest time seen) are forgotten."""
    wifi_model: str = "wifi-eq3"
    """``wifi-eq3`` (the paper) or ``wifi-fingerprint`` (ours: union RMS, ``WifiFingerprintParams``; needs
    its range model in the calibration). Candidates are found by the same strongest-N index either way."""
    fingerprint: WifiFingerprintParams = field(default_factory=WifiFingerprintParams)

    def __post_init__(self) -> None:
        if self.wifi_model not in WIFI_MODELS:
            raise ValueError(
                f"unknown WiFi encounter model {self.wifi_model!r}; valid: {', '.join(WIFI_MODELS)}"
            )


@dataclass(frozen=True)
class Detection:
    t_ms: int
    user_a: str
    user_b: str
    model: int  # MODEL_WIFI, MODEL_WIFI_FINGERPRINT or MODEL_BLUETOOTH
    feature: float  # Sim (dB) or averaged RSS (dBm)


@dataclass(frozen=True)
class RangedDetection(Detection):
    """A detection with its calibrated range and R (``EncounterDetector.ranged``)."""

    distance_m: float
    variance_m2: float


@dataclass
class _Scan:
    user: str
    t_ms: int
    top: dict[int, float]  # the strongest N APs: interned BSSID -> RSS
    fresh: dict[int, float]  # every fresh AP (the fingerprint model compares these)
    arrival: int  # order of arrival: candidates are compared in it, whatever their times


@dataclass
class _Bucket:
    """The retained scans that hold one AP among their strongest N, sorted by scan time, so the scans
    within the pair window are found by bisection (retention is ten times the window: a linear pass over
    the bucket was most of a scan's cost in a busy building)."""

    times: list[int] = field(default_factory=list)
    scans: list[_Scan] = field(default_factory=list)

    def add(self, scan: _Scan) -> None:
        at = bisect_right(self.times, scan.t_ms)
        self.times.insert(at, scan.t_ms)
        self.scans.insert(at, scan)

    def within(self, lo_ms: int, hi_ms: int) -> list[_Scan]:
        return self.scans[bisect_left(self.times, lo_ms) : bisect_right(self.times, hi_ms)]

    def forget_before(self, horizon_ms: int) -> None:
        cut = bisect_left(self.times, horizon_ms)
        if cut:
            del self.times[:cut]
            del self.scans[:cut]


def _arrival(scan: _Scan) -> int:
    return scan.arrival


def union_rms(a: dict[int, float], b: dict[int, float], floor_dbm: float) -> float:
    """RMS dB difference over the union of two scans' APs, a missing AP counting as ``floor_dbm``."""
    keys = a.keys() | b.keys()
    if not keys:
        return math.inf
    total = sum(
        (max(a.get(k, floor_dbm), floor_dbm) - max(b.get(k, floor_dbm), floor_dbm)) ** 2 for k in keys
    )
    return math.sqrt(total / len(keys))


def eq3_sparse(top_a: dict[int, float], top_b: dict[int, float]) -> tuple[float, int]:
    """Eq. 3 over the APs common to both scans' strongest N: (||U1 - U2|| / n, n); (inf, 0) if none."""
    common = top_a.keys() & top_b.keys()
    n = len(common)
    if n == 0:
        return math.inf, 0
    return math.sqrt(sum((top_a[k] - top_b[k]) ** 2 for k in common)) / n, n


class EncounterDetector:
    def __init__(self, params: DetectionParams, calibration: Calibration) -> None:
        self.params = params
        self.calibration = calibration
        self._ap_ids: dict[str, int] = {}
        self._scans: deque[_Scan] = deque()  # in order of arrival
        self._by_ap: dict[int, _Bucket] = defaultdict(_Bucket)
        self._arrivals = 0
        self._bt: dict[tuple[str, str], deque[tuple[int, float]]] = {}
        self._newest_ms = 0
        self._bt_pruned_at = 0
        self.n_candidates = 0
        if params.wifi_model == "wifi-fingerprint" and calibration.wifi_fingerprint is None:
            raise ValueError(
                "the wifi-fingerprint encounter model needs its range model in the calibration "
                "(fit it with `crowdslam calibrate`)"
            )

    # ------------------------------------------------------------------ WiFi
    def add_scan(
        self, user: str, t_ms: int, bssids: list[str], rss: np.ndarray, last_seen_ms: np.ndarray
    ) -> list[Detection]:
        """Index one scan and return the encounters it completes with other users' scans.
        ``last_seen_ms`` is -1 where the phone did not say."""
        p = self.params
        fresh = fresh_mask(t_ms, last_seen_ms, p.stale_ap_ms)
        keep = np.flatnonzero(fresh)
        if keep.size == 0:
            return []
        order = keep[np.argsort(-rss[keep], kind="stable")[: p.wifi.strongest_n]]
        top = {self._intern(bssids[i]): float(rss[i]) for i in order}
        by_fingerprint = p.wifi_model == "wifi-fingerprint"
        fresh_aps = {self._intern(bssids[i]): float(rss[i]) for i in keep} if by_fingerprint else top
        self._advance(t_ms)
        found: dict[int, _Scan] = {}
        window = p.scan_pair_window_ms
        for ap in top:
            bucket = self._by_ap.get(ap)
            if bucket is None:
                continue
            for other in sorted(bucket.within(t_ms - window, t_ms + window), key=_arrival):
                if other.user != user:
                    found[other.arrival] = other
        passing: list[tuple[_Scan, float]] = []
        for other in found.values():
            self.n_candidates += 1
            if by_fingerprint:
                feature = union_rms(fresh_aps, other.fresh, p.fingerprint.floor_dbm)
                if feature < p.fingerprint.threshold_db:
                    passing.append((other, feature))
                continue
            sim, n = eq3_sparse(top, other.top)
            if n >= p.wifi.min_common and sim < p.wifi.threshold_db:
                passing.append((other, sim))
        kind = MODEL_WIFI_FINGERPRINT if by_fingerprint else MODEL_WIFI
        out = [Detection(max(t_ms, other.t_ms), user, other.user, kind, f) for other, f in passing]
        scan = _Scan(user, t_ms, top, fresh_aps, self._arrivals)
        self._arrivals += 1
        self._scans.append(scan)
        for ap in top:
            self._by_ap[ap].add(scan)
        return out

    def _intern(self, bssid: str) -> int:
        key = bssid.lower()
        ident = self._ap_ids.get(key)
        if ident is None:
            ident = self._ap_ids[key] = len(self._ap_ids)
        return ident

    # ------------------------------------------------------------------ Bluetooth
    def add_sighting(self, receiver: str, sender: str, t_ms: int, rss_dbm: float) -> Detection | None:
        """One phone heard another; returns an encounter when the pair-averaged RSS passes the cut-off."""
        if receiver == sender:
            return None
        self._advance(t_ms)
        pair = (min(receiver, sender), max(receiver, sender))
        history = self._bt.setdefault(pair, deque())
        history.append((t_ms, rss_dbm))
        while history and t_ms - history[0][0] >= self.params.bt_smoothing_ms:
            history.popleft()
        smoothed = sum(r for _, r in history) / len(history)
        if smoothed < self.params.bluetooth.cutoff_dbm:
            return None
        return Detection(t_ms, receiver, sender, MODEL_BLUETOOTH, smoothed)

    def ranged(self, detections: list[Detection]) -> list[RangedDetection]:
        """The detections with their calibrated ranges and R, one vectorised lookup per model (only the
        detections chosen as human anchors need them)."""
        distance = np.empty(len(detections))
        variance = np.empty(len(detections))
        models = np.array([d.model for d in detections], dtype=np.int64)
        features = np.array([d.feature for d in detections], dtype=np.float64)
        for model in np.unique(models):
            at = models == model
            distance[at], variance[at] = self.range_model(int(model)).range_and_variance(features[at])
        return [
            RangedDetection(d.t_ms, d.user_a, d.user_b, d.model, d.feature, float(r), float(v))
            for d, r, v in zip(detections, distance, variance, strict=True)
        ]

    def range_model(self, model: int) -> RangeModel:
        """The calibrated range model behind detections of ``model``."""
        if model == MODEL_BLUETOOTH:
            return self.calibration.bluetooth
        if model == MODEL_WIFI_FINGERPRINT and self.calibration.wifi_fingerprint is not None:
            return self.calibration.wifi_fingerprint
        if model == MODEL_WIFI:
            return self.calibration.wifi
        raise ValueError(f"no range model for encounter model {model}")

    # ------------------------------------------------------------------ shared

    def _advance(self, t_ms: int) -> None:
        """Forget scans and sightings that can no longer pair with anything new."""
        if t_ms <= self._newest_ms:
            return
        self._newest_ms = t_ms
        horizon = t_ms - self.params.retention_ms
        touched: set[int] = set()
        while self._scans and self._scans[0].t_ms < horizon:
            touched.update(self._scans.popleft().top)
        for ap in touched:
            bucket = self._by_ap[ap]
            bucket.forget_before(horizon)
            if not bucket.times:
                del self._by_ap[ap]
        if len(self._bt) > self._bt_pruned_at + 1024:
            self._bt = {k: v for k, v in self._bt.items() if v and v[-1][0] >= horizon}
            self._bt_pruned_at = len(self._bt)

    @property
    def n_indexed_scans(self) -> int:
        return len(self._scans)
