"""The server-side sensor front-end of phones that send raw IMU: per user, the online PDR (steps) and the
building-anchor detectors (turns, strong beacons, strong WiFi APs, changes of floor), all state carried
between batches.

Phones that count their own steps are expected to run their own detectors too (they send
``anchor_detections``); the tracker only calls this for batches with raw IMU and no steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_core.sensing import detectors as anchor_detectors
from slam_core.sensing.detectors import AnchorEvents, DetectorParams, DetectorState
from slam_core.sensing.lift import detect_lift_rides
from slam_core.sensing.magnetic import detect_magnetic_anomalies
from slam_core.sensing.pdr.online import ImuSamples, PdrParams, PdrState, PdrSteps, drop_stale, pdr_steps
from slam_core.sensing.vertical import detect_floor_changes


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
        self.fired = {
            "turn": 0,
            "beacon": 0,
            "wifi": 0,
            "elevator": 0,
            "stairs": 0,
            "escalator": 0,
            "magnetic": 0,
        }

    def forget(self, user: str) -> None:
        self._pdr.pop(user, None)
        self._detect.pop(user, None)

    def has_barometer(self, user: str) -> bool:
        """Whether the user's phone has sent pressure (since the server last forgot its sensors)."""
        detect = self._detect.get(user)
        return detect is not None and not math.isnan(detect.vertical.last_t)

    def floor_changes(
        self, user: str, pressure: np.ndarray, step_t: np.ndarray, phone_found: bool = False
    ) -> tuple[AnchorEvents, int]:
        """The changes of floor in the barometer of a phone that counts its own steps (and so sends no raw
        IMU), with the steps it sent; and how many samples were dropped as already consumed. Once the phone
        has sent a change of floor of its own (``phone_found``, in this batch or before), none is reported
        from here: the phone's detector has them."""
        if self.detectors is None:
            return AnchorEvents.empty(), 0
        detect = self._detect.setdefault(user, DetectorState())
        detect.phone_finds_floors |= phone_found
        floors, dropped = self._floor_changes(detect, pressure, step_t)
        if detect.phone_finds_floors:
            return AnchorEvents.empty(), dropped
        return anchor_detectors.merge_events([], [], self.detectors.turn_type, floors), dropped

    def _floor_changes(
        self, detect: DetectorState, pressure: np.ndarray, step_t: np.ndarray
    ) -> tuple[list[tuple[int, int, str, int, float]], int]:
        """``slam_core.sensing.vertical`` on one batch's pressure (samples already consumed are dropped: a
        late or re-sent batch) as (report time, type, "", arrival, rise) rows, and the count dropped."""
        assert self.detectors is not None
        v = self.detectors.vertical
        dropped = 0
        last = detect.vertical.last_t
        if pressure.size and not np.isnan(last) and pressure[0, 0] <= last:
            fresh = pressure[pressure[:, 0] > last]
            dropped = pressure.shape[0] - fresh.shape[0]
            pressure = fresh
        if not (v.enabled and pressure.size):
            return [], dropped
        changes = detect_floor_changes(detect.vertical, v, pressure, step_t)
        for c in changes:
            self.fired[
                {v.elevator_type: "elevator", v.stairs_type: "stairs"}.get(c.type_index, "escalator")
            ] += 1
        return [(c.t_ms, c.type_index, "", c.observed_t_ms, c.change_m) for c in changes], dropped

    def process(self, user: str, imu: ImuSamples, radio: RadioArrays) -> FrontEndOutput:
        state = self._pdr.setdefault(user, PdrState())
        imu, dropped = drop_stale(state, imu)
        steps = pdr_steps(state, imu, self.pdr)
        if self.detectors is None:
            return FrontEndOutput(steps, AnchorEvents.empty(), dropped)
        p = self.detectors
        detect = self._detect.setdefault(user, DetectorState())
        headings = anchor_detectors.step_headings(detect, steps.azimuth_rad, steps.turn_rad)
        turns = anchor_detectors.detect_turns(detect, p, steps.t_ms, headings) if p.turns else []
        radio_events = anchor_detectors.detect_radio(
            detect, p, radio.scan_t, radio.scan_offsets, radio.scan_bssid, radio.scan_rss,
            radio.scan_last_seen, radio.beacon_t, radio.beacon_mac, radio.beacon_rss,
        )  # fmt: skip
        floors, stale = self._floor_changes(detect, imu.pressure, steps.t_ms)
        dropped += stale
        if not (p.vertical.enabled and imu.pressure.size) and (
            p.lift.enabled and np.isnan(detect.vertical.last_t) and imu.acc.size
        ):  # no barometer: lift rides from the accelerometer
            ride_t, rise = detect_lift_rides(detect.lift, p.lift, imu.acc, steps.t_ms)
            floors = [
                (int(t), p.lift.type_index, "", int(t), float(r)) for t, r in zip(ride_t, rise, strict=True)
            ]
            self.fired["elevator"] += len(floors)
        if p.magnetic.enabled and imu.mag.size:
            anomalies = detect_magnetic_anomalies(detect.magnetic, p.magnetic, imu.mag)
            floors += [(t, p.magnetic.type_index, "", peak, math.nan) for t, peak in anomalies]
            self.fired["magnetic"] += len(anomalies)
        self.fired["turn"] += len(turns)
        self.fired["beacon"] += sum(e[1] == p.beacon_type for e in radio_events)
        self.fired["wifi"] += sum(e[1] == p.wifi_type for e in radio_events)
        return FrontEndOutput(
            steps, anchor_detectors.merge_events(turns, radio_events, p.turn_type, floors), dropped
        )
