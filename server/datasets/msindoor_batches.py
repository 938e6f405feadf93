"""Indoor Location 2.0 traces as the sensor batches a phone would post (about one second each)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from schemas.common import MAX_TIME_MS, MIN_TIME_MS
from schemas.sensors import (
    BeaconSighting,
    RotationVectorStream,
    SensorBatch,
    Vector3Stream,
    WifiAp,
    WifiScan,
)
from server.datasets.msindoor import Trace, iter_windows


def _vector(rows: np.ndarray) -> Vector3Stream | None:
    if len(rows) == 0:
        return None
    return Vector3Stream(
        t_ms=rows[:, 0].astype(np.int64).tolist(),
        x=rows[:, 1].tolist(),
        y=rows[:, 2].tolist(),
        z=rows[:, 3].tolist(),
    )


def _rotation(rows: np.ndarray) -> RotationVectorStream | None:
    if len(rows) == 0:
        return None
    xyz = rows[:, 1:4]
    norm = np.linalg.norm(xyz, axis=1, keepdims=True)
    xyz = np.where(norm > 1.0, xyz / np.maximum(norm, 1e-12), xyz)  # rounding in the file can exceed 1
    return RotationVectorStream(
        t_ms=rows[:, 0].astype(np.int64).tolist(),
        x=xyz[:, 0].tolist(),
        y=xyz[:, 1].tolist(),
        z=xyz[:, 2].tolist(),
    )


def _valid_time(t: int) -> int | None:
    return t if MIN_TIME_MS <= t <= MAX_TIME_MS else None


def trace_batches(
    trace: Trace, building_id: str, device_id: str, window_ms: int = 1000, first_seq: int = 0
) -> Iterator[SensorBatch]:
    """One batch per window with data, in time order; ``batch_id`` is ``<device>-<seq>``."""
    for _end, batch in trace_windows(trace, building_id, device_id, window_ms, first_seq):
        yield batch


def trace_windows(
    trace: Trace,
    building_id: str,
    device_id: str,
    window_ms: int = 1000,
    first_seq: int = 0,
    cuts: Sequence[int] = (),
) -> Iterator[tuple[int, SensorBatch]]:
    """``trace_batches`` with each batch's window end, windows also split at the ``cuts`` times."""
    seq = first_seq
    walk = trace.path.stem
    for start, end in iter_windows(trace, window_ms, cuts):

        def window(rows: np.ndarray, start: int = start, end: int = end) -> np.ndarray:
            return rows[(rows[:, 0] >= start) & (rows[:, 0] < end)] if len(rows) else rows

        streams = {name: window(rows) for name, rows in trace.streams.items()}
        scans = [
            WifiScan(
                t_ms=s.t_ms,
                aps=[
                    WifiAp(
                        bssid=s.bssid[i],
                        ssid=s.ssid[i][:64],
                        rssi_dbm=float(s.rssi_dbm[i]),
                        frequency_mhz=int(s.frequency_mhz[i]),
                        last_seen_ms=_valid_time(int(s.last_seen_ms[i]))
                        if s.last_seen_ms[i] <= s.t_ms + 1000
                        else None,
                    )
                    for i in range(len(s.bssid))
                    if -120 <= s.rssi_dbm[i] <= 0 and 2400 <= s.frequency_mhz[i] <= 7125
                ],
            )
            for s in trace.wifi
            if start <= s.t_ms < end
        ]
        beacons = [
            BeaconSighting(
                t_ms=t, mac=mac, uuid=uuid[:36], major=major, minor=minor, rssi_dbm=rssi, tx_power_dbm=tx
            )
            for t, uuid, major, minor, tx, rssi, _distance, mac in trace.beacons
            if start <= t < end and -120 <= rssi <= 0 and -120 <= tx <= 20
        ]
        if not any(len(r) for r in streams.values()) and not scans and not beacons:
            continue
        yield (
            end,
            SensorBatch(
                building_id=building_id,
                device_id=device_id,
                user_id=walk,
                batch_id=f"{device_id}-{seq}",
                seq=seq,
                accelerometer=_vector(streams.get("accelerometer", np.zeros((0, 4)))),
                gyroscope=_vector(streams.get("gyroscope", np.zeros((0, 4)))),
                magnetometer=_vector(streams.get("magnetometer", np.zeros((0, 4)))),
                rotation_vector=_rotation(streams.get("rotation_vector", np.zeros((0, 4)))),
                wifi_scans=[s for s in scans if s.aps],
                bluetooth=beacons,
            ),
        )
        seq += 1
