"""Replay a recording through the ingestion path: offline (in-process, a fresh SQLite) or to a server."""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from schemas.api import BatchReceipt
from schemas.estimates import Estimate
from server.buildings.config import TrackingConfig
from server.buildings.host import BuildingHost
from server.buildings.submissions import Submission
from server.errors import ProblemError
from server.ingestion.decoding import decode_batch
from server.recordings.recorder import RecordedBatch
from server.settings import Settings
from server.simulation.crowd_client import post_batch
from server.slam.config import load_calibration, tracker_params
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade
from server.store.models import BuildingRow


@dataclass
class ReplayReport:
    batches: int = 0
    applied: int = 0
    duplicates: int = 0
    late: int = 0
    rejected: int = 0
    steps: int | None = None
    """Steps the server's PDR found in the batches' raw IMU (an offline replay counts them; a server's
    ``/metrics`` says them as ``crowdslam_steps_detected``)."""
    latest: dict[str, Estimate] = field(default_factory=dict)

    def count(self, receipt: BatchReceipt) -> None:
        self.batches += 1
        self.applied += receipt.status == "applied"
        self.duplicates += receipt.status == "duplicate"
        self.late += receipt.status == "late"
        if receipt.estimate is not None:
            self.latest[receipt.estimate.user_id] = receipt.estimate

    def summary(self) -> dict[str, object]:
        return {
            "batches": self.batches,
            "applied": self.applied,
            "duplicates": self.duplicates,
            "late": self.late,
            "rejected": self.rejected,
            **({} if self.steps is None else {"steps": self.steps}),
            "latest": {u: e.model_dump(mode="json") for u, e in sorted(self.latest.items())},
        }


def replay_offline(
    batches: Iterable[RecordedBatch], settings: Settings, progress: Callable[[int], None] | None = None
) -> ReplayReport:
    """Every batch through dedupe, ordering, conversion, tracking and persistence, in a fresh database,
    with the settings' seed and parameters: the same path as the server, minus HTTP."""
    report = ReplayReport()
    with tempfile.TemporaryDirectory() as tmp:
        engine = make_engine(f"sqlite:///{Path(tmp) / 'replay.sqlite3'}")
        upgrade(engine)
        sessions = make_session_factory(engine)
        params, calibration = tracker_params(settings), load_calibration(settings.encounter_calibration)
        buildings: dict[str, BuildingHost] = {}
        try:
            for recorded in batches:
                try:
                    batch = decode_batch(recorded.raw, settings.max_batch_bytes)
                    submission = Submission.of(batch, recorded.raw, recorded.received_ns)
                except ProblemError:
                    report.rejected += 1
                    continue
                building = buildings.get(batch.building_id)
                if building is None:
                    with sessions.begin() as session:
                        session.add(
                            BuildingRow(id=batch.building_id, name=batch.building_id, rotation_rad=0.0)
                        )
                    building = BuildingHost(
                        batch.building_id, sessions, TrackingConfig(params, calibration, settings.seed)
                    )
                    buildings[batch.building_id] = building
                result = building.process([submission])
                receipt = result.receipts[0]
                if isinstance(receipt, ProblemError):
                    report.rejected += 1
                else:
                    report.count(receipt)
                if progress is not None:
                    progress(1)
            report.steps = sum(b.counters.steps_detected for b in buildings.values())
        finally:
            engine.dispose()
    return report


def replay_to_server(
    batches: Iterable[RecordedBatch],
    client: httpx.Client,
    operator_key: str,
    progress: Callable[[int], None] | None = None,
) -> ReplayReport:
    """Post every batch as recorded; device keys are minted with the operator key, buildings created."""
    report = ReplayReport()
    auth = {"Authorization": f"Bearer {operator_key}"}
    keys: dict[tuple[str, str], str] = {}
    for recorded in batches:
        try:
            batch = decode_batch(recorded.raw, 1 << 30)
        except ProblemError:
            report.rejected += 1
            continue
        ident = (batch.building_id, batch.device_id)
        if ident not in keys:
            client.post(
                "/v1/buildings", json={"id": batch.building_id, "name": batch.building_id}, headers=auth
            )
            response = client.post(
                f"/v1/buildings/{batch.building_id}/keys",
                json={"scope": "device", "device_id": batch.device_id},
                headers=auth,
            )
            if response.status_code != 201:
                raise RuntimeError(f"cannot mint a device key: {response.status_code} {response.text}")
            keys[ident] = response.json()["key"]
        response = post_batch(client, batch.building_id, recorded.raw, keys[ident])
        if response.status_code == 200:
            report.count(BatchReceipt.model_validate_json(response.content))
        else:
            report.rejected += 1
        if progress is not None:
            progress(1)
    return report
