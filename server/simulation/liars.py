"""Users who lie, for the evaluation: the DynamicSLAM paper warns that a malicious user can feed others
wrong human anchors. A liar's phone posts what an attacker controlling it could:

- WiFi scans copied from a victim's (the first honest user's) scans of the same second, so that the server
  detects a perfect WiFi encounter between the two wherever they are;
- Bluetooth sightings of the victim at -45 dBm every second (a close encounter, made up);
- position fixes far from the truth: its start 40 m off, and a false fix every ten seconds.

The honest users' error with and without liars measures what the outlier gating holds (the encounter
selection's prediction gate, the likelihood's outlier term)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from schemas.common import Position
from schemas.sensors import PeerSighting, PositionFix, SensorBatch, WifiScan
from server.simulation.phones import advertised_id, device_id

OFFSET_M = 40.0
FALSE_FIX_EVERY = 10


def liar_devices(n_users: int, liars: int) -> set[str]:
    """The last ``liars`` users lie (the first is the victim, always honest)."""
    if liars >= n_users:
        raise ValueError(f"{liars} liars leave no honest user among {n_users}")
    return {device_id(u) for u in range(n_users - liars, n_users)}


def lying(batches: Iterable[SensorBatch], liars: set[str], victim: int = 0) -> Iterator[SensorBatch]:
    """The crowd's batches in order, the liars' rewritten: the victim's scans of the last second copied,
    sightings of the victim made up, fixes moved far away."""
    victim_device = device_id(victim)
    recent_scans: list[WifiScan] = []  # the victim's latest batch's scans
    for batch in batches:
        if batch.device_id == victim_device:
            recent_scans = list(batch.wifi_scans)
        if batch.device_id not in liars:
            yield batch
            continue
        span = batch.time_span_ms()
        t = span[1] if span is not None else None
        update: dict[str, object] = {}
        if recent_scans and t is not None:
            update["wifi_scans"] = [s.model_copy(update={"t_ms": t}) for s in recent_scans[:1]]
        if t is not None:
            update["bluetooth"] = [
                PeerSighting(t_ms=t, peer_advertised_id=advertised_id(victim), rssi_dbm=-45.0)
            ]
        landmarks = [
            m.model_copy(
                update={"position": Position(x_m=m.position.x_m + OFFSET_M, y_m=m.position.y_m + OFFSET_M)}
            )
            if isinstance(m, PositionFix)
            else m
            for m in batch.landmarks
        ]
        if batch.seq % FALSE_FIX_EVERY == FALSE_FIX_EVERY - 1 and batch.steps:
            landmarks.append(
                PositionFix(
                    t_ms=batch.steps[-1].t_ms,
                    position=Position(x_m=OFFSET_M, y_m=-OFFSET_M),
                    sigma_m=0.5,
                )
            )
        update["landmarks"] = landmarks
        yield batch.model_copy(update=update)
