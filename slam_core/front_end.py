"""The server-side sensor front-end of phones that send raw IMU: per user, the online PDR (steps) and the
building-anchor detectors (turns, strong beacons, strong WiFi APs), all state carried between batches.

Phones that count their own steps are expected to run their own detectors too (they send
``anchor_detections``); the tracker only calls this for batches with raw IMU and no steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_core.detectors import (
    AnchorEvents,
    DetectorParams,
    DetectorState,
    detect_radio,
    detect_turns,
    merge_events,
    step_headings,
)
from slam_core.pdr.frontend import ImuSamples, PdrParams, PdrState, PdrSteps, drop_stale, pdr_steps


@dataclass(frozen=True)
class RadioArrays:
    """One batch's radio readings as the tracker holds them."""

    scan_t: np.ndarray
    scan_offsets: np.ndarray
    scan_bssid: tuple[str, ...]
    scan_rss: np.ndarray
    scan_last_seen: np.ndarray
    beacon_t: np.ndarray
    beacon_mac: tuple[str, ...]
    beacon_rss: np.ndarray


@dataclass(frozen=True)
class FrontEndOutput:
    steps: PdrSteps
    anchors: AnchorEvents
    imu_samples_dropped: int


class FrontEnd:
    def __init__(self, pdr: PdrParams, detectors: DetectorParams | None) -> None:
        self.pdr = pdr
        self.detectors = detectors
        self._pdr: dict[str, PdrState] = {}
        self._detect: dict[str, DetectorState] = {}
        self.fired = {"turn": 0, "beacon": 0, "wifi": 0}

    def forget(self, user: str) -> None:
        self._pdr.pop(user, None)
        self._detect.pop(user, None)

    def process(self, user: str, imu: ImuSamples, radio: RadioArrays) -> FrontEndOutput:
        state = self._pdr.setdefault(user, PdrState())
        imu, dropped = drop_stale(state, imu)
        steps = pdr_steps(state, imu, self.pdr)
        if self.detectors is None:
            return FrontEndOutput(steps, AnchorEvents.empty(), dropped)
        p = self.detectors
        detect = self._detect.setdefault(user, DetectorState())
        headings = step_headings(detect, steps.azimuth_rad, steps.turn_rad)
        turns = detect_turns(detect, p, steps.t_ms, headings) if p.turns else []
        radio_events = detect_radio(
            detect, p, radio.scan_t, radio.scan_offsets, radio.scan_bssid, radio.scan_rss,
            radio.scan_last_seen, radio.beacon_t, radio.beacon_mac, radio.beacon_rss,
        )  # fmt: skip
        self.fired["turn"] += len(turns)
        self.fired["beacon"] += sum(e[1] == p.beacon_type for e in radio_events)
        self.fired["wifi"] += sum(e[1] == p.wifi_type for e in radio_events)
        return FrontEndOutput(steps, merge_events(turns, radio_events, p.turn_type), dropped)
