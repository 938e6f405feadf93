"""Drive a simulated crowd against a running server over HTTP, as real phones would."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import httpx
import numpy as np

from schemas.api import BatchReceipt
from schemas.buildings import Building, Floor
from schemas.sensors import PeerSighting, SensorBatch
from server.simulation.phones import EPOCH_MS, device_id, known_anchors, simulated_batches
from slam_core.sim.simulation import Simulation


class CrowdClientError(RuntimeError):
    pass


@dataclass
class CrowdReport:
    batches: int = 0
    duplicates: int = 0
    errors: int = 0
    encounters: int = 0
    error_m: list[float] = field(default_factory=list)
    receipts: list[BatchReceipt] = field(default_factory=list)
    seconds: float = 0.0

    def summary(self) -> dict[str, float | int]:
        err = np.array(self.error_m) if self.error_m else np.array([np.nan])
        return {
            "batches": self.batches,
            "errors": self.errors,
            "duplicates": self.duplicates,
            "encounters": self.encounters,
            "median_m": float(np.median(err)),
            "p90_m": float(np.percentile(err, 90)),
            "seconds": self.seconds,
        }


def _check(response: httpx.Response, allowed: tuple[int, ...] = (200, 201, 204)) -> httpx.Response:
    if response.status_code not in allowed:
        raise CrowdClientError(
            f"{response.request.method} {response.request.url}: {response.status_code} {response.text}"
        )
    return response


def prepare_building(client: httpx.Client, building_id: str, operator_key: str, sim: Simulation) -> None:
    """Create the building (if new) and pin the scenario's operator-known anchors."""
    auth = {"Authorization": f"Bearer {operator_key}"}
    floor = sim.scenario["floor"]
    body = Building(
        id=building_id,
        name=f"Simulated {sim.scenario.raw.get('name', 'floor')}",
        floors=[Floor(level=0, name="Ground", width_m=floor["width_m"], height_m=floor["height_m"])],
    )
    _check(client.post("/v1/buildings", json=body.model_dump(mode="json"), headers=auth), (201, 409))
    for k, anchor in enumerate(known_anchors(sim)):
        payload = {
            "type": anchor.type.value,
            "position": {"x_m": anchor.position[0], "y_m": anchor.position[1]},
        }
        _check(client.put(f"/v1/buildings/{building_id}/anchors/known-{k}", json=payload, headers=auth))


def device_keys(
    client: httpx.Client, building_id: str, operator_key: str, n_users: int, prefix: str = ""
) -> dict[str, str]:
    auth = {"Authorization": f"Bearer {operator_key}"}
    keys = {}
    for u in range(n_users):
        device = prefix + device_id(u)
        response = _check(
            client.post(
                f"/v1/buildings/{building_id}/keys",
                json={"scope": "device", "device_id": device},
                headers=auth,
            )
        )
        keys[device] = response.json()["key"]
    return keys


def retire_crowd(
    client: httpx.Client, building_id: str, operator_key: str, devices: dict[str, str | None]
) -> int:
    """A crowd that has finished walking leaves: each device's user is forgotten (``DELETE .../users/{id}``)
    and its key revoked (``devices`` maps each to its key's prefix, or None), so the building shows and
    keeps only the people still there. Returns the users forgotten (a device that never placed its user has
    none)."""
    auth = {"Authorization": f"Bearer {operator_key}"}
    forgotten = 0
    for device, prefix in devices.items():
        gone = client.delete(f"/v1/buildings/{building_id}/users/{device}", headers=auth)
        if gone.status_code != 404:
            _check(gone)
            forgotten += 1
        if prefix is not None:
            revoked = client.delete(f"/v1/buildings/{building_id}/keys/{prefix}", headers=auth)
            if revoked.status_code != 404:  # revoked already
                _check(revoked)
    return forgotten


def crowd_epoch_ms(now_ms: int, duration_s: float, speed: float, lead_s: float = 60.0) -> int:
    """Phone time of a crowd's simulation time 0, so that its batches carry times near the wall clock:
    posted at ``speed`` times real time (0: as fast as the server answers), a crowd's simulated clock gains
    on the wall clock; it starts early enough that no batch is more than ``lead_s`` ahead (the server refuses
    batches five minutes ahead)."""
    gain_s = duration_s * (1.0 - (1.0 / speed if speed > 0 else 0.0))
    return now_ms - round(max(0.0, gain_s - lead_s) * 1000.0)


def post_crowd(
    client: httpx.Client,
    sim: Simulation,
    building_id: str,
    keys: dict[str, str],
    speed: float = 0.0,
    prefix: str = "",
    progress: Callable[[int], None] | None = None,
    epoch_ms: int = EPOCH_MS,
) -> CrowdReport:
    """Post every batch in time order, one at a time (so the run is reproducible). ``speed`` > 0 paces the
    posts at that multiple of real time; 0 posts as fast as the server answers. ``prefix`` renames devices
    and users so repeated runs are new people; ``epoch_ms`` is the phone time of simulation time 0 (a later
    crowd in the same building comes later)."""
    report = CrowdReport()
    started = time.perf_counter()
    for batch in simulated_batches(sim, building_id, epoch_ms):
        if prefix:
            batch = _renamed(batch, prefix)
        if speed > 0:
            due = _first_time_s(batch, epoch_ms) / speed
            delay = due - (time.perf_counter() - started)
            if delay > 0:
                time.sleep(delay)
        response = post_batch(
            client, building_id, batch.model_dump_json(exclude_none=True), keys[batch.device_id]
        )
        report.batches += 1
        if response.status_code != 200:
            report.errors += 1
            continue
        receipt = BatchReceipt.model_validate_json(response.content)
        report.receipts.append(receipt)
        report.duplicates += receipt.duplicate
        report.encounters += len(receipt.encounters)
        if receipt.estimate is not None and batch.steps:
            user = int(batch.device_id.rsplit("-", 1)[-1])
            truth = sim.true_position(user, (receipt.estimate.t_ms - epoch_ms) / 1000.0)
            report.error_m.append(
                float(
                    np.hypot(
                        receipt.estimate.position.x_m - truth[0], receipt.estimate.position.y_m - truth[1]
                    )
                )
            )
        if progress is not None:
            progress(1)
    report.seconds = time.perf_counter() - started
    return report


def _first_time_s(batch: SensorBatch, epoch_ms: int) -> float:
    span = batch.time_span_ms()
    return 0.0 if span is None else (span[0] - epoch_ms) / 1000.0


def _renamed(batch: SensorBatch, prefix: str) -> SensorBatch:

    bluetooth = [
        s.model_copy(update={"peer_advertised_id": prefix + s.peer_advertised_id})
        if isinstance(s, PeerSighting)
        else s
        for s in batch.bluetooth
    ]
    return batch.model_copy(
        update={
            "device_id": prefix + batch.device_id,
            "batch_id": prefix + batch.batch_id,
            "ble_advertised_id": None
            if batch.ble_advertised_id is None
            else prefix + batch.ble_advertised_id,
            "bluetooth": bluetooth,
        }
    )


def post_batch(
    client: httpx.Client, building_id: str, body: str | bytes, key: str, max_waits: int = 20
) -> httpx.Response:
    """Post one batch as a phone should: on 429, wait as ``Retry-After`` says and send it again."""
    for _ in range(max_waits):
        response = client.post(
            f"/v1/buildings/{building_id}/batches",
            content=body,
            headers={"Authorization": f"Bearer {key}", "Content-Type": "application/json"},
        )
        if response.status_code != 429:
            return response
        time.sleep(float(response.headers.get("retry-after", "1")))
    return response
