"""The arrays that go in and out of ``BuildingTracker.apply``: a batch, and what the tracker made of it."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from slam_core.encounters.detection import RangedDetection
from slam_core.sensing.pdr.online import ImuSamples
from slam_core.wifi.pairs import fresh_mask


def _i64(n: int = 0) -> np.ndarray:
    return np.zeros(n, dtype=np.int64)


def _f64(n: int = 0) -> np.ndarray:
    return np.zeros(n, dtype=np.float64)


def check_values(
    user: str,
    readings: Sequence[np.ndarray | Sequence[float]],
    sigmas: np.ndarray | Sequence[float],
    lengths: np.ndarray | Sequence[float],
) -> None:
    """The values a user batch may hold, as arrays or as the lists they are made from: every reading
    finite, fix sigmas > 0, step lengths >= 0; else ValueError. One pass over the non-empty ones: most of a
    batch's fields are empty."""
    if all(isinstance(r, list | tuple) for r in (*readings, sigmas, lengths)):
        # the front's lists (a batch's few dozen values): Python's own checks, no array made to be dropped
        finite = all(all(map(math.isfinite, r)) for r in readings)
        low_sigma = bool(sigmas) and min(sigmas) <= 0
        negative = bool(lengths) and min(lengths) < 0
    else:
        present = [r for r in readings if len(r)]
        finite = not present or bool(np.isfinite(np.concatenate(present)).all())
        low_sigma = bool(len(sigmas) and np.min(sigmas) <= 0)
        negative = bool(len(lengths) and np.min(lengths) < 0)
    if not finite or low_sigma or negative:
        raise ValueError(f"user batch of {user!r}: non-finite values, sigma <= 0 or negative lengths")


@dataclass(frozen=True)
class UserBatch:
    """One user's share of a batch, as arrays. Times are epoch ms; headings are radians."""

    user: str
    ble_id: str | None = None
    fix_t: np.ndarray = field(default_factory=_i64)
    fix_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    fix_sigma: np.ndarray = field(default_factory=_f64)
    fix_azimuth: np.ndarray = field(default_factory=_f64)  # clockwise from north, NaN when unknown
    step_t: np.ndarray = field(default_factory=_i64)
    step_length: np.ndarray = field(default_factory=_f64)
    step_azimuth: np.ndarray = field(default_factory=_f64)  # clockwise from north, NaN when not given
    step_turn: np.ndarray = field(default_factory=_f64)  # counter-clockwise change, NaN when not given
    step_heading_offset: np.ndarray = field(default_factory=_f64)
    """Per step (or empty): the north reference the PDR front-end added to its gyroscope yaw (NaN: none)."""
    detect_t: np.ndarray = field(default_factory=_i64)
    detect_type: np.ndarray = field(default_factory=_i64)
    scan_t: np.ndarray = field(default_factory=_i64)
    scan_offsets: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    scan_bssid: tuple[str, ...] = ()
    scan_rss: np.ndarray = field(default_factory=_f64)
    scan_last_seen: np.ndarray = field(default_factory=_i64)  # -1 when the phone did not say
    peer_t: np.ndarray = field(default_factory=_i64)
    peer_id: tuple[str, ...] = ()  # the heard phones' advertised ids
    peer_rss: np.ndarray = field(default_factory=_f64)
    beacon_t: np.ndarray = field(default_factory=_i64)
    beacon_mac: tuple[str, ...] = ()  # fixed Bluetooth beacons heard (not phones)
    beacon_rss: np.ndarray = field(default_factory=_f64)
    detect_signature: tuple[str, ...] = ()  # per detection: the transmitter's identity, "" for none
    detect_observed_t: np.ndarray = field(default_factory=_i64)  # per detection: when at the anchor
    detect_rise: np.ndarray = field(default_factory=_f64)
    """Per detection (or empty: none): a change of floor's signed rise in metres (NaN: not one, or not
    known)."""
    fix_level: np.ndarray = field(default_factory=_i64)
    """Per fix (or empty: all on level 0): the floor the fix names."""
    imu: ImuSamples | None = None
    """Raw IMU for the PDR front-end; ignored when the phone sent its own steps."""

    def __post_init__(self) -> None:
        f, s, d, c, p = (
            self.fix_t.size,
            self.step_t.size,
            self.detect_t.size,
            self.scan_t.size,
            self.peer_t.size,
        )
        shapes_ok = (
            self.fix_xy.shape == (f, 2)
            and self.fix_sigma.shape == (f,)
            and self.fix_azimuth.shape == (f,)
            and self.step_length.shape == self.step_azimuth.shape == self.step_turn.shape == (s,)
            and self.step_heading_offset.size in (0, s)
            and self.detect_type.shape == (d,)
            and self.scan_offsets.shape == (c + 1,)
            and int(self.scan_offsets[0]) == 0
            and len(self.scan_bssid)
            == self.scan_rss.size
            == self.scan_last_seen.size
            == int(self.scan_offsets[-1])
            and len(self.peer_id) == self.peer_rss.size == p
            and len(self.beacon_mac) == self.beacon_rss.size == self.beacon_t.size
            and len(self.detect_signature) in (0, d)
            and self.detect_observed_t.size in (0, d)
            and self.detect_rise.size in (0, d)
            and self.fix_level.size in (0, f)
        )
        if not shapes_ok:
            raise ValueError(f"user batch of {self.user!r}: inconsistent array shapes")
        check_values(
            self.user,
            (self.fix_xy.ravel(), self.fix_sigma, self.step_length, self.scan_rss, self.peer_rss),
            self.fix_sigma,
            self.step_length,
        )

    def fix_floor(self, i: int) -> int:
        """The floor fix ``i`` names."""
        return int(self.fix_level[i]) if self.fix_level.size else 0

    def rise(self, i: int) -> float:
        """Detection ``i``'s rise (NaN: none)."""
        return float(self.detect_rise[i]) if self.detect_rise.size else math.nan

    def fresh_scan(self, c: int, stale_ms: int) -> tuple[int, list[str], np.ndarray]:
        """Scan ``c``'s time and its fresh entries (``slam_core.wifi.pairs.fresh_mask``): BSSIDs and RSS."""
        lo, hi = int(self.scan_offsets[c]), int(self.scan_offsets[c + 1])
        t = int(self.scan_t[c])
        fresh = fresh_mask(t, self.scan_last_seen[lo:hi], stale_ms)
        bssids = [str(x) for x, f in zip(self.scan_bssid[lo:hi], fresh, strict=True) if f]
        return t, bssids, self.scan_rss[lo:hi][fresh]


@dataclass
class UserReport:
    """What happened to one user's batch."""

    status: str = "awaiting_fix"  # "placing" while a cold start is not confident; "tracking" once placed
    cold_started: bool = False  # placed among the crowd's candidate places in this call, with no fix
    steps_detected: int = 0  # by the PDR front-end from raw IMU
    imu_samples_dropped: int = 0  # older than what the front-end had consumed (late or re-sent)
    anchors_detected: int = 0  # by the front-end's detectors
    signatures_applied: int = 0  # signature anchors observed as position measurements
    signatures_gated: int = 0  # ... skipped as inconsistent with the user's cloud
    steps_applied: int = 0
    steps_dropped: int = 0  # before the first fix, out of time order, or with no heading reference
    detections_applied: int = 0
    fixes_applied: int = 0
    recentred: int = 0
    fingerprint_fixes: int = 0  # scans localised on the crowd fingerprint map and applied
    fingerprint_fix: tuple[float, float] | None = None
    """Where the call's fingerprint fix placed the user (carried to its latest step), when it got one."""
    clock_restarted: bool = False  # the phone's clock went back: the user's timeline restarted here
    anchor_joins: list[tuple[int, int]] = field(default_factory=list)
    """Per building-anchor detection applied (not signatures): its time and the crowd anchor it joined."""


@dataclass(frozen=True)
class EstimateRow:
    t_ms: int
    x: float
    y: float
    cov: tuple[float, float, float]  # xx, xy, yy
    best: tuple[float, float]
    heading: float  # counter-clockwise from east
    floor: int = 0
    floor_probability: float = 1.0
    """How sure the filter is of ``floor`` (``slam_core.tracking.floors``)."""


@dataclass(frozen=True)
class EncounterResult:
    detection: RangedDetection
    applied: bool
    places: tuple[float, ...] | None = None
    """Where the two were at the encounter's time (x_a, y_a, x_b, y_b), as their filters believed then."""
    level: int = 0
    """The floor they met on."""


@dataclass(frozen=True)
class ZoneEvent:
    user: str
    zone_id: str
    kind: str  # "enter", "exit" or "dwell"
    t_ms: int
    """When it happened: the last time the probability inside crossed one half (``slam_core.zones.
    presence``)."""
    probability: float
    """The probability that the user was inside when the event was decided."""
    told_ms: int = 0
    """When it was decided (the user's time of the estimate that made it sure)."""


@dataclass
class TrackerOutcome:
    reports: dict[str, UserReport]
    estimates: dict[str, EstimateRow]  # of the users whose batches were applied (peers: with their next)
    encounters: list[EncounterResult]  # the detections chosen as human anchors (applied, or gated)
    anchors_changed: list[int]  # crowd indices created or re-estimated
    detections: int = 0  # encounter detections, chosen or not
    zone_events: list[ZoneEvent] = field(default_factory=list)  # entries, exits, dwells of the call's users
