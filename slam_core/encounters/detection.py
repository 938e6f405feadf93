"""Online encounter detection across one building's users (DynamicSLAM Section 4.1.2), as scans and
sightings arrive.

WiFi: each scan is compared, by Eq. 3, with the other users' scans within ``scan_pair_window_ms``. Eq. 3
only compares APs common to both scans' strongest N, so a scan can only pass against scans sharing one of
its strongest N APs: an inverted index from those APs to recent scans finds every candidate, and the cost
of a scan does not grow with the number of users in the building. The scans and the index live in arrays
(``slam_core.encounters.scan_store``), and a compiled kernel compares a whole tracker call's scans
(``slam_core.encounters.search``, with the measures of ``slam_core.wifi.similarity``).

Bluetooth: a phone's sighting of another phone's advertised id, averaged per pair (both directions) over
``bt_smoothing_ms`` (one sighting period), is an encounter above the -90 dBm cut-off.

Every detection is reported; which ones become human anchors is chosen by the tracker from the filters'
estimates (``slam_core.encounters.selection``), and only those are ranged
(calibrated range and R, ``ranged``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slam_core.background_call import BackgroundCall
from slam_core.encounters.models import (
    MODEL_BLUETOOTH,
    MODEL_WIFI,
    MODEL_WIFI_FINGERPRINT,
    Calibration,
    DetectionParams,
    RangeModel,
)
from slam_core.encounters.scan_store import ScanStore
from slam_core.encounters.sighting_pairs import SightingPairs
from slam_core.wifi.pairs import fresh_mask


@dataclass(frozen=True)
class Detection:
    t_ms: int
    user_a: str
    user_b: str
    model: int  # MODEL_WIFI, MODEL_WIFI_FINGERPRINT or MODEL_BLUETOOTH
    feature: float  # Sim (dB) or averaged RSS (dBm)


@dataclass(frozen=True)
class DetectionArrays:
    """Detections as arrays (a busy building finds thousands per call; only the few chosen become
    ``Detection`` objects). Users are the detector's interned ids (``EncounterDetector.user_name``)."""

    t_ms: np.ndarray  # int64
    user_a: np.ndarray  # int64
    user_b: np.ndarray  # int64
    model: np.ndarray  # int64
    feature: np.ndarray  # float64

    @classmethod
    def empty(cls) -> DetectionArrays:
        none = np.zeros(0, dtype=np.int64)
        return cls(none, none, none, none, np.zeros(0))

    @classmethod
    def concatenate(cls, parts: Sequence[DetectionArrays]) -> DetectionArrays:
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in _DETECTION_FIELDS))

    def __len__(self) -> int:
        return int(self.t_ms.size)

    def subset(self, index: np.ndarray) -> DetectionArrays:
        return DetectionArrays(*(getattr(self, f)[index] for f in _DETECTION_FIELDS))


_DETECTION_FIELDS = ("t_ms", "user_a", "user_b", "model", "feature")


@dataclass(frozen=True)
class RangedDetection(Detection):
    """A detection with its calibrated range and R (``EncounterDetector.ranged``)."""

    distance_m: float
    variance_m2: float


@dataclass(frozen=True)
class ScanBatch:
    """WiFi scans in arrival order: scan c, of ``users[c]`` at ``t_ms[c]``, has the entries
    ``offsets[c]:offsets[c + 1]`` of ``bssids``, ``rss`` and ``last_seen_ms`` (-1: the phone did not say)."""

    users: Sequence[str]
    t_ms: np.ndarray
    offsets: np.ndarray
    bssids: Sequence[str]
    rss: np.ndarray
    last_seen_ms: np.ndarray


@dataclass(frozen=True)
class _PreparedScans:
    """A call's kept scans as the scan store takes them (``EncounterDetector._prepared``)."""

    t_ms: np.ndarray
    user: np.ndarray
    top_ap: np.ndarray
    top_rss: np.ndarray
    fresh_offsets: np.ndarray
    fresh_ap: np.ndarray
    fresh_rss: np.ndarray
    n_aps: int


class EncounterDetector:
    def __init__(self, params: DetectionParams, calibration: Calibration, scan_capacity: int = 1024) -> None:
        self.params = params
        self.calibration = calibration
        self._ap_ids: dict[str, int] = {}
        self._user_ids: dict[str, int] = {}
        self._user_names: list[str] = []
        self._store = ScanStore(params.wifi.strongest_n, scan_capacity)
        self._bt = SightingPairs()  # each pair's sightings within the smoothing window
        self._pending: BackgroundCall[DetectionArrays] | None = None  # scans compared on a thread
        if params.wifi_model == "wifi-fingerprint" and calibration.wifi_fingerprint is None:
            raise ValueError(
                "the wifi-fingerprint encounter model needs its range model in the calibration "
                "(fit it with `crowdslam calibrate`)"
            )

    def __getstate__(self) -> dict[str, object]:
        if self._pending is not None:
            raise RuntimeError("cannot pickle a detector while scans are being compared")
        state = dict(self.__dict__)
        del state["_pending"]  # a thread handle
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
        self._pending = None

    @property
    def n_indexed_scans(self) -> int:
        return self._store.live

    def user_id(self, user: str) -> int:
        """The interned id detections carry for ``user``."""
        ident = self._user_ids.get(user)
        if ident is None:
            ident = self._user_ids[user] = len(self._user_names)
            self._user_names.append(user)
        return ident

    def user_name(self, ident: int) -> str:
        return self._user_names[ident]

    def bluetooth_pairs(self) -> list[tuple[str, str]]:
        """The pairs whose sightings are kept, least recently heard first (each by its users' names, the
        earlier interned first)."""
        return [(self._user_names[a], self._user_names[b]) for a, b in self._bt.pairs()]

    @property
    def n_user_ids(self) -> int:
        """User ids interned so far (ids are ``0 .. n_user_ids - 1``, never reused)."""
        return len(self._user_names)

    def known_user_id(self, user: str) -> int | None:
        """``user``'s id if it has one (unlike ``user_id``, never interns)."""
        return self._user_ids.get(user)

    def to_detections(self, found: DetectionArrays) -> list[Detection]:
        names = self._user_names
        return [
            Detection(int(t), names[int(a)], names[int(b)], int(m), float(f))
            for t, a, b, m, f in zip(
                found.t_ms, found.user_a, found.user_b, found.model, found.feature, strict=True
            )
        ]

    # ------------------------------------------------------------------ WiFi
    def add_scans(
        self,
        users: Sequence[str],
        t_ms: np.ndarray,
        offsets: np.ndarray,
        bssids: Sequence[str],
        rss: np.ndarray,
        last_seen_ms: np.ndarray,
    ) -> DetectionArrays:
        """Index scans (in arrival order; scan c's entries are ``offsets[c]:offsets[c + 1]``) and return the
        encounters each completes with other users' earlier scans. ``last_seen_ms`` is -1 where the phone
        did not say. A scan without fresh APs is neither indexed nor compared."""
        scans = ScanBatch(users, t_ms, offsets, bssids, rss, last_seen_ms)
        return self.start_scans(scans, background=False).result()

    def start_scans(self, scans: ScanBatch, background: bool) -> BackgroundCall[DetectionArrays]:
        """``add_scans``, with the comparison (the compiled kernel, which releases the GIL) on a thread of
        its own when ``background``: the caller goes on with work that does not touch this detector and
        collects the detections with ``result()``. The BSSIDs and users are interned here, in the caller's
        thread, so the thread touches only the scan store, and the outcome is the same either way."""
        if self._pending is not None:
            raise RuntimeError("the previous scans' detections have not been collected")
        prepared = self._prepared(scans)
        if prepared is None:
            return BackgroundCall(DetectionArrays.empty, False)
        pending = BackgroundCall(lambda: self._compare(prepared), background, self._collected)
        self._pending = pending
        return pending

    def _collected(self) -> None:
        self._pending = None

    def _prepared(self, scans: ScanBatch) -> _PreparedScans | None:
        """The kept scans as the scan store's arrays (None when no scan has a fresh AP): each scan's fresh
        entries (``fresh_mask``), its ``strongest_n`` strongest of them (ties in arrival order), their BSSIDs
        interned in that order and a BSSID repeated within a scan counted once (at its first place, with its
        last RSS, as a dict keeps it). The masks and sorts run over all of a call's entries at once."""
        p = self.params
        n_top = p.wifi.strongest_n
        offsets = np.asarray(scans.offsets, dtype=np.int64)
        base, end = int(offsets[0]), int(offsets[-1])  # entry k of the call is entry base + k of the arrays
        scan_of = np.repeat(np.arange(offsets.size - 1), np.diff(offsets))
        t = np.asarray(scans.t_ms, dtype=np.int64)
        rss = np.asarray(scans.rss, dtype=np.float64)[base:end]
        last_seen = np.asarray(scans.last_seen_ms)[base:end]
        fresh = np.flatnonzero(fresh_mask(t[scan_of], last_seen, p.stale_ap_ms))
        if fresh.size == 0:
            return None
        # each scan's fresh entries from the strongest, ties in arrival order (lexsort is stable)
        ranked = fresh[np.lexsort((-rss[fresh], scan_of[fresh]))]
        ranked_scan = scan_of[ranked]
        kept = np.unique(ranked_scan)  # the scans with a fresh entry, in arrival order
        first = np.searchsorted(ranked_scan, kept)
        rank = np.arange(ranked.size) - np.repeat(first, np.diff(np.append(first, ranked.size)))
        top = ranked[rank < n_top]
        intern = self._intern
        bssids = scans.bssids[base:end]
        by_fingerprint = p.wifi_model == "wifi-fingerprint"
        if by_fingerprint:
            fresh_by_scan = np.split(fresh, np.searchsorted(scan_of[fresh], kept[1:]))
        top_scan = scan_of[top]
        top_first = np.searchsorted(top_scan, kept)
        top_ends = np.append(top_first[1:], top.size)
        rows = np.full((kept.size, n_top), -1, dtype=np.int64)
        values = np.zeros((kept.size, n_top))
        fresh_ap: list[int] = []
        fresh_rss: list[float] = []
        fresh_offsets = [0]
        top_rss = rss[top].tolist()
        for j, (lo, hi) in enumerate(zip(top_first.tolist(), top_ends.tolist(), strict=True)):
            ids = [intern(bssids[i]) for i in top[lo:hi].tolist()]
            if len(set(ids)) == len(ids):
                rows[j, : len(ids)] = ids
                values[j, : len(ids)] = top_rss[lo:hi]
            else:  # a repeated BSSID counts once
                once = dict(zip(ids, top_rss[lo:hi], strict=True))
                rows[j, : len(once)] = list(once)
                values[j, : len(once)] = list(once.values())
            if by_fingerprint:
                entries = fresh_by_scan[j].tolist()
                heard = {intern(bssids[i]): float(rss[i]) for i in entries}
                fresh_ap += heard
                fresh_rss += heard.values()
            fresh_offsets.append(len(fresh_ap))
        user_id = self.user_id
        users = scans.users
        return _PreparedScans(
            t[kept],
            np.array([user_id(users[c]) for c in kept.tolist()], dtype=np.int64),
            rows,
            values,
            np.array(fresh_offsets, dtype=np.int64),
            np.array(fresh_ap, dtype=np.int64),
            np.array(fresh_rss, dtype=np.float64),
            len(self._ap_ids),
        )

    def _compare(self, scans: _PreparedScans) -> DetectionArrays:
        """Store the prepared scans and compare each with the live ones before it (touches only the store)."""
        p = self.params
        out_t, out_new, other, feature = self._store.add(
            scans.t_ms, scans.user, scans.top_ap, scans.top_rss, scans.fresh_offsets, scans.fresh_ap,
            scans.fresh_rss, scans.n_aps, p,
        )  # fmt: skip
        model = MODEL_WIFI_FINGERPRINT if p.wifi_model == "wifi-fingerprint" else MODEL_WIFI
        return DetectionArrays(out_t, scans.user[out_new], other, np.full(out_t.size, model), feature)

    def add_scan(
        self, user: str, t_ms: int, bssids: list[str], rss: np.ndarray, last_seen_ms: np.ndarray
    ) -> list[Detection]:
        """One scan (``add_scans`` of one), its detections as objects."""
        found = self.add_scans(
            [user], np.array([t_ms]), np.array([0, len(bssids)]), bssids, rss, last_seen_ms
        )
        return self.to_detections(found)

    def _intern(self, bssid: str) -> int:
        key = bssid.lower()
        ident = self._ap_ids.get(key)
        if ident is None:
            ident = self._ap_ids[key] = len(self._ap_ids)
        return ident

    # ------------------------------------------------------------------ Bluetooth
    def add_sightings(
        self, receivers: Sequence[str], senders: Sequence[str], t_ms: np.ndarray, rss_dbm: np.ndarray
    ) -> DetectionArrays:
        """Phones heard other phones (in arrival order); an encounter each time a pair's RSS, averaged over
        both directions and ``bt_smoothing_ms``, passes the cut-off (``SightingPairs``). A phone hearing
        itself is no sighting."""
        kept = [k for k, (r, s) in enumerate(zip(receivers, senders, strict=True)) if r != s]
        if not kept:
            return DetectionArrays.empty()
        user_id = self.user_id
        pairs = np.array(  # interned in arrival order, receiver first
            [(user_id(receivers[k]), user_id(senders[k])) for k in kept], dtype=np.int64
        )
        return self.add_sighting_ids(
            pairs[:, 0], pairs[:, 1], np.asarray(t_ms)[kept], np.asarray(rss_dbm)[kept]
        )

    def add_sighting_ids(
        self, receivers: np.ndarray, senders: np.ndarray, t_ms: np.ndarray, rss_dbm: np.ndarray
    ) -> DetectionArrays:
        """``add_sightings`` of users given by their interned ids (``user_id``), none hearing itself."""
        p = self.params
        t = np.asarray(t_ms, dtype=np.int64)
        passed, smoothed = self._bt.add(
            receivers, senders, t, rss_dbm, p.bt_smoothing_ms, p.retention_ms, p.bluetooth.cutoff_dbm
        )
        if not passed.size:
            return DetectionArrays.empty()
        return DetectionArrays(
            t[passed],
            np.asarray(receivers, dtype=np.int64)[passed],
            np.asarray(senders, dtype=np.int64)[passed],
            np.full(passed.size, MODEL_BLUETOOTH, dtype=np.int64),
            smoothed,
        )

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
