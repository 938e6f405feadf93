"""The tracker's encounter stage: WiFi scans and Bluetooth sightings matched across the building's users
(Eq. 3, the RSS cut-off) on one floor, the detections the selector chooses on the filters' estimates
(``slam_core.encounters.selection.choose_readings``), applied as human anchors (Algorithm 1).

``EncounterStage`` owns what the stage keeps between calls: the detector (its scans and sightings), the
selector (its pairs' cooldowns), each detector user id's filter slot, and each slot's columns for carrying
readings in time. The tracker tells it when a user takes or leaves a slot and what each call's users
reported. Pure numerics.
"""

from __future__ import annotations

import numpy as np

from slam_core.background_call import BackgroundCall
from slam_core.encounters.detection import DetectionArrays, EncounterDetector, ScanBatch
from slam_core.encounters.models import Calibration
from slam_core.encounters.selection import EncounterSelector, choose_readings
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.tracking.batches import EncounterResult, UserBatch
from slam_core.tracking.carry import SlotColumns, carried_since, carry_variance
from slam_core.tracking.params import TrackerParams
from slam_core.tracking.trails import Trails, UserTrack

BACKGROUND_SCANS = 16
"""A call with this many scans compares them on a thread of its own while the tracker runs the rounds and
the fingerprint fixes (the kernel releases the GIL). Below it, starting a thread (~0.1 ms) costs more than it
hides."""


class EncounterStage:
    def __init__(self, params: TrackerParams, calibration: Calibration) -> None:
        self.apply_human_anchors = params.filter.use_human_anchors
        self.detector = EncounterDetector(params.detection, calibration)
        self.selector = EncounterSelector(params.selection)
        self.slots = DetectorSlots()
        self.columns = SlotColumns()

    # ------------------------------------------------------------------ the users' slots and columns
    def admit(self, user: str, slot: int) -> None:
        """A user starts in this slot."""
        self.columns.reset(slot)
        self.slots.set(self.detector, user, slot)

    def remove(self, user: str) -> None:
        """A user leaves its slot (the slot may be given to another)."""
        self.slots.set(self.detector, user, -1)

    def restart(self, slot: int) -> None:
        """The user in this slot restarts its timeline: nothing before can be carried along it."""
        self.columns.reset(slot)

    def begin(self, tracks: list[UserTrack]) -> None:
        """Before a call's events (``SlotColumns.begin``)."""
        self.columns.begin(tracks)

    def heard(self, tracks: list[UserTrack], heard_t_ms: list[int], trails: Trails) -> None:
        """After a call's events (``SlotColumns.update``)."""
        self.columns.update(tracks, heard_t_ms, trails)

    # ------------------------------------------------------------------ a call's encounters
    def start(self, batches: list[UserBatch]) -> BackgroundCall[DetectionArrays]:
        """Hand the call's WiFi scans to the detector (``EncounterDetector.start_scans``): in a busy call they
        are compared on a thread of their own, and nothing else may use the detector until ``collect`` has
        taken them."""
        scan_users: list[str] = []
        scan_t, scan_offsets, scan_rss, scan_seen = [], [0], [], []
        bssids: list[str] = []
        for b in batches:
            if b.scan_t.size:
                scan_users += [b.user] * b.scan_t.size
                scan_t.append(b.scan_t)
                scan_offsets += (scan_offsets[-1] + b.scan_offsets[1:]).tolist()
                bssids += b.scan_bssid
                scan_rss.append(b.scan_rss)
                scan_seen.append(b.scan_last_seen)
        if not scan_users:
            return BackgroundCall(DetectionArrays.empty, False)
        scans = ScanBatch(
            scan_users,
            np.concatenate(scan_t),
            np.array(scan_offsets, dtype=np.int64),
            bssids,
            np.concatenate(scan_rss),
            np.concatenate(scan_seen),
        )
        return self.detector.start_scans(scans, background=len(scan_users) >= BACKGROUND_SCANS)

    def collect(
        self,
        filters: DynamicSlam,
        batches: list[UserBatch],
        users: dict[str, UserTrack],
        by_ble: dict[str, str],
        scans: BackgroundCall[DetectionArrays],
        trails: Trails,
    ) -> tuple[list[EncounterResult], int]:
        """The encounters chosen among this call's detections (its scans' from ``start``, and its Bluetooth
        sightings'), applied as human anchors when the mode has them, and how many detections there were.
        The detections stay arrays until the few chosen ones are ranged (a busy building finds thousands)."""
        detector = self.detector
        user_id = detector.user_id
        receivers: list[int] = []
        senders: list[int] = []
        peer_t, peer_rss = [], []
        for b in batches:  # the phones heard, by their users' detector ids (a user hearing itself is none)
            if not b.peer_t.size:
                continue
            peers = [by_ble.get(ident) for ident in b.peer_id]
            heard = [k for k, peer in enumerate(peers) if peer is not None and peer != b.user]
            if heard:
                receivers += [user_id(b.user)] * len(heard)  # interned before its first peer, as one by one
                senders += [user_id(peers[k]) for k in heard]  # type: ignore[arg-type]
                peer_t.append(b.peer_t[heard])
                peer_rss.append(b.peer_rss[heard])
        sightings = (
            detector.add_sighting_ids(
                np.array(receivers, dtype=np.int64),
                np.array(senders, dtype=np.int64),
                np.concatenate(peer_t),
                np.concatenate(peer_rss),
            )
            if receivers
            else DetectionArrays.empty()
        )
        found = DetectionArrays.concatenate([scans.result(), sightings])
        slots = self.slots.of(detector, users, np.concatenate([found.user_a, found.user_b]))  # both at once
        slot_a, slot_b = slots[: len(found)], slots[len(found) :]
        tracked = (slot_a >= 0) & (slot_b >= 0)
        if tracked.any():  # a pair heard through a ceiling is no encounter: both on one floor, as believed
            levels = filters.levels
            tracked &= levels[np.maximum(slot_a, 0)] == levels[np.maximum(slot_b, 0)]
        usable = np.flatnonzero(tracked)
        if usable.size == 0:
            return [], len(found)
        mask, offset, carry_var, places = choose_readings(
            filters.means,
            detector,
            self.selector,
            found.subset(usable),
            slot_a[usable],
            slot_b[usable],
            _TrailCarrier(self.columns, trails, self.slots, detector, users),
        )
        keep = usable[mask]
        chosen = detector.ranged(detector.to_detections(found.subset(keep)))
        levels = filters.levels[slot_a[keep]].tolist()
        if not chosen or not self.apply_human_anchors:
            return [
                EncounterResult(d, False, tuple(p), lv)
                for d, p, lv in zip(chosen, places.tolist(), levels, strict=True)
            ], len(found)
        outcome = filters.observe_encounters(
            slot_a[keep],
            slot_b[keep],
            np.array([d.distance_m for d in chosen]),
            np.array([d.variance_m2 for d in chosen]) + carry_var,
            offset,
        )
        results = [
            EncounterResult(d, bool(a), tuple(p), lv)
            for d, a, p, lv in zip(chosen, outcome.applied, places.tolist(), levels, strict=True)
        ]
        return results, len(found)


class _TrailCarrier:
    """``ReadingCarrier`` over the tracker's users: the slots' columns, and the users' trails, found by their
    detector ids' slots. Called after the call's events (``EncounterStage.heard``), when the columns' last
    event of every tracked user is its track's."""

    def __init__(
        self,
        columns: SlotColumns,
        trails: Trails,
        slots: DetectorSlots,
        detector: EncounterDetector,
        users: dict[str, UserTrack],
    ) -> None:
        self.columns = columns
        self.trails = trails
        self.slots = slots
        self.detector = detector
        self.users = users

    @property
    def last_t_ms(self) -> np.ndarray:
        return self.columns.last_t_ms

    def reach(self, slots: np.ndarray, t_ms: np.ndarray) -> np.ndarray:
        return self.columns.reach(slots, t_ms)

    def extrapolated(self, slots: np.ndarray, t_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.columns.extrapolated(slots, t_ms)

    def carried_since(
        self, user_ids: np.ndarray, which: np.ndarray, t_ms: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        slots = self.slots.of(self.detector, self.users, user_ids)[which]
        return carried_since(self.trails, slots, self.columns.last_t_ms[slots], t_ms)

    def carry_variance(self, walked_m: np.ndarray) -> np.ndarray:
        return carry_variance(walked_m)


class DetectorSlots:
    """Each detector user id's filter slot (-1: not tracked), kept between calls rather than looked up again
    every call for every user a busy call's detections name. The stage sets it wherever a user's slot changes
    (a start, a removal); ids the detector interned since the last call are looked up when they first
    appear."""

    def __init__(self) -> None:
        self._table = np.empty(0, dtype=np.int64)

    def of(
        self, detector: EncounterDetector, users: dict[str, UserTrack], user_ids: np.ndarray
    ) -> np.ndarray:
        known = self._table.size
        if detector.n_user_ids > known:
            names = [detector.user_name(i) for i in range(known, detector.n_user_ids)]
            tracks = [users.get(name) for name in names]
            new = [u.slot if u is not None and u.slot >= 0 else -1 for u in tracks]
            self._table = np.concatenate([self._table, np.array(new, dtype=np.int64)])
        result: np.ndarray = self._table[user_ids]
        return result

    def set(self, detector: EncounterDetector, user: str, slot: int) -> None:
        ident = detector.known_user_id(user)
        if ident is not None and ident < self._table.size:
            self._table[ident] = slot
