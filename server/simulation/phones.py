"""A simulated crowd as the phones would post it: one-second sensor batches per user, in time order.

Each user's first batch carries its start fix (the scenario's noisy start position and heading, on the floor
the user starts on); steps carry the phone's azimuth (none while the user stands in a lift or on an
escalator); phones with a barometer send its samples; building-anchor detections (and, from phones without
a barometer, the ways between floors their accelerometer finds) are sent as the phone's own detections; WiFi
scans list one synthetic BSSID per simulated access point; Bluetooth sightings name the heard phone's
advertised id.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from schemas.anchors import AnchorType
from schemas.common import Position
from schemas.sensors import (
    AnchorDetection,
    PeerSighting,
    PositionFix,
    ScalarStream,
    SensorBatch,
    Step,
    WifiAp,
    WifiScan,
)
from slam_core.filter.params import ANCHOR_TYPES
from slam_core.sim.simulation import Simulation

EPOCH_MS = 1_767_225_600_000
"""Simulated time 0 is 2026-01-01T00:00:00Z (any fixed instant would do; batches must carry epoch times)."""
WINDOW_MS = 1_000


@dataclass(frozen=True)
class KnownAnchor:
    position: tuple[float, float]
    type: AnchorType
    level: int = 0


def device_id(user: int) -> str:
    return f"sim-phone-{user:03d}"


def advertised_id(user: int) -> str:
    return f"ble-{user:03d}"


def bssid(ap: int) -> str:
    return "02:00:00:00:" + f"{(ap >> 8) & 0xFF:02x}:{ap & 0xFF:02x}"


def known_anchors(sim: Simulation) -> list[KnownAnchor]:
    """The operator-known anchors of the simulated world (entered by the operator before the crowd walks)."""
    w = sim.world
    levels = w.anchor_levels()
    return [
        KnownAnchor(
            (float(w.anchor_xy[k, 0]), float(w.anchor_xy[k, 1])),
            AnchorType(ANCHOR_TYPES[int(w.anchor_type[k])]),
            int(levels[k]),
        )
        for k in np.flatnonzero(w.anchor_known)
    ]


def simulated_batches(sim: Simulation, building_id: str, epoch_ms: int = EPOCH_MS) -> Iterator[SensorBatch]:
    """Every user's batches, ordered by window end then user (the order a crowd posting in real time has).
    Simulation time 0 is phone time ``epoch_ms``."""
    per_user = [list(_user_batches(sim, u, building_id, epoch_ms)) for u in range(len(sim.users))]
    keyed = [(end, u, k) for u, batches in enumerate(per_user) for k, (end, _) in enumerate(batches)]
    for _, u, k in sorted(keyed):
        yield per_user[u][k][1]


def _user_batches(
    sim: Simulation, user: int, building_id: str, epoch_ms: int
) -> Iterator[tuple[int, SensorBatch]]:
    def _ms(t_s: float) -> int:
        return epoch_ms + round(t_s * 1000.0)

    tr = sim.users[user]
    step_ms = np.array([_ms(t) for t in tr.t[1:]], dtype=np.int64)
    stepped = np.ones(step_ms.size, dtype=bool) if tr.is_step is None else tr.is_step
    pressure_ms = np.array([_ms(t) for t in tr.pressure[:, 0]], dtype=np.int64)
    scan_ms = np.array([_ms(t) for t in tr.scan_t], dtype=np.int64)
    receive = np.flatnonzero(sim.bt_pair[:, 0] == user) if sim.bt_t.size else np.zeros(0, dtype=np.int64)
    bt_ms = np.array([_ms(sim.bt_t[i]) for i in receive], dtype=np.int64)
    bt_heard = (sim.bt_rss[receive] >= -120.0) & (sim.bt_rss[receive] <= 0.0)
    detections: dict[int, tuple[int, float | None]] = {
        k: (a, None) for k, a in zip(tr.anchor_step.tolist(), tr.anchor_detected_type.tolist(), strict=True)
    }
    for k, a, rise in tr.way_detections:  # the phone's own: a way between floors wins a shared moment
        detections[k] = (a, None if math.isnan(rise) else rise)
    start_ms = _ms(tr.t[0])
    last_ms = max(int(step_ms[-1]) if step_ms.size else start_ms, int(scan_ms.max(initial=start_ms)))
    for seq, window_start in enumerate(range(start_ms, last_ms + 1, WINDOW_MS)):
        window_end = window_start + WINDOW_MS
        landmarks: list[PositionFix] = []
        if seq == 0:
            landmarks.append(
                PositionFix(
                    t_ms=start_ms,
                    position=Position(x_m=float(tr.start_fix[0]), y_m=float(tr.start_fix[1])),
                    sigma_m=float(sim.scenario["users"]["start_fix_sigma_m"]),
                    azimuth_rad=_wrap(math.pi / 2 - tr.start_heading_fix),
                    floor=tr.level_at(tr.t[0]),
                )
            )
        inside = (step_ms >= window_start) & (step_ms < window_end)
        in_window = np.flatnonzero(stepped & inside)
        steps = [
            Step(
                t_ms=int(step_ms[k]),
                length_m=float(min(max(tr.step_length_obs[k], 0.01), 3.0)),
                azimuth_rad=_wrap(math.pi / 2 - float(tr.step_heading_obs[k])),
            )
            for k in in_window
        ]
        moved = np.flatnonzero(inside)  # with a step or not
        anchor_detections = [
            AnchorDetection(
                t_ms=int(step_ms[k]),
                type=AnchorType(ANCHOR_TYPES[detections[k + 1][0]]),
                rise_m=detections[k + 1][1],
            )
            for k in moved.tolist()
            if k + 1 in detections
        ]
        scans = []
        for c in np.flatnonzero((scan_ms >= window_start) & (scan_ms < window_end)):
            heard = np.flatnonzero(~np.isnan(tr.scan_rss[c]) & (tr.scan_rss[c] >= -120.0))
            if heard.size:
                aps = [
                    WifiAp(
                        bssid=bssid(int(a)), rssi_dbm=round(float(tr.scan_rss[c, a]), 1), frequency_mhz=2437
                    )
                    for a in heard
                ]
                scans.append(WifiScan(t_ms=int(scan_ms[c]), aps=aps))
        in_bt = np.flatnonzero(bt_heard & (bt_ms >= window_start) & (bt_ms < window_end))
        sightings = [
            PeerSighting(
                t_ms=int(t_ms),
                peer_advertised_id=advertised_id(int(sim.bt_pair[i, 1])),
                rssi_dbm=round(float(sim.bt_rss[i]), 1),
            )
            for t_ms, i in zip(bt_ms[in_bt], receive[in_bt], strict=True)
        ]
        in_pressure = np.flatnonzero((pressure_ms >= window_start) & (pressure_ms < window_end))
        pressure = (
            ScalarStream(
                t_ms=pressure_ms[in_pressure].tolist(),
                value=[round(float(v), 3) for v in tr.pressure[in_pressure, 1]],
            )
            if in_pressure.size
            else None
        )
        yield (
            window_end,
            SensorBatch(
                building_id=building_id,
                device_id=device_id(user),
                batch_id=f"{device_id(user)}-{seq}",
                seq=seq,
                ble_advertised_id=advertised_id(user),
                steps=steps,
                wifi_scans=scans,
                bluetooth=list(sightings),
                landmarks=list(landmarks),
                anchor_detections=anchor_detections,
                pressure=pressure,
            ),
        )


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi
