"""Over real HTTP and WebSocket: a simulated crowd posts to a running server; the estimates it gets back
equal the offline engine's on the same batches with the same seed, and a dashboard sees them live."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from server.app import create_app
from server.cli.background_server import free_port, running_server
from server.ingestion.convert import anchor_type_index, building_context, to_user_batch
from server.settings import Settings
from server.simulation.crowd_client import device_keys, post_crowd, prepare_building
from server.simulation.phones import known_anchors, simulated_batches
from server.slam.config import load_calibration, tracker_params
from slam_core.sim.simulation import Scenario, simulate
from slam_core.tracking.tracker import BuildingTracker
from tests.conftest import TESTBED
from tests.server.conftest import migrate_with_operator


def _small_testbed() -> Scenario:
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = 6
    raw["users"]["walk_length_m"] = 60.0
    return Scenario.from_dict(raw)


@pytest.fixture(params=[False, True], ids=["building-threads", "building-processes"])
def live_server(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[tuple[str, str, Settings]]:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, seed=3, building_processes=request.param)
    with running_server(create_app(settings), "127.0.0.1", free_port()) as base:
        yield base, operator, settings


def test_live_estimates_equal_the_offline_engine(live_server: tuple[str, str, Settings]) -> None:
    base, operator, settings = live_server
    sim = simulate(_small_testbed(), 1)
    received: list[dict[str, object]] = []
    batched: list[dict[str, object]] = []
    with httpx.Client(base_url=base, timeout=60) as client:
        prepare_building(client, "sim", operator, sim)
        keys = device_keys(client, "sim", operator, len(sim.users))
        dashboard = client.post(
            "/v1/buildings/sim/keys",
            json={"scope": "dashboard"},
            headers={"Authorization": f"Bearer {operator}"},
        ).json()["key"]
        ws_url = base.replace("http", "ws", 1) + f"/v1/buildings/sim/live?token={dashboard}"
        with connect(ws_url) as ws, connect(ws_url + "&batch=true") as batched_ws:
            report = post_crowd(client, sim, "sim", keys)
            metrics = client.get("/metrics").text
            for socket_, sink in ((ws, received), (batched_ws, batched)):
                while True:
                    try:
                        sink.append(json.loads(socket_.recv(timeout=1.0)))
                    except TimeoutError:
                        break
        with (
            pytest.raises(ConnectionClosed, match="4401"),  # the documented close code, not a bare 403
            connect(base.replace("http", "ws", 1) + "/v1/buildings/sim/live?token=wrong") as bad,
        ):
            bad.recv(timeout=5)
    assert report.errors == 0
    assert report.batches > 100
    # offline: the same batches through the same conversion and tracker, same seed and parameters
    tracker = BuildingTracker(tracker_params(settings), load_calibration(None), seed=settings.seed)
    for anchor in known_anchors(sim):
        tracker.pin_anchor(np.array(anchor.position), anchor_type_index(anchor.type))
    ctx = building_context("sim", tracker, {}, None, None)
    live = iter(report.receipts)
    compared = fixes = 0
    for batch in simulated_batches(sim, "sim"):
        outcome = tracker.apply([to_user_batch(batch, ctx).user_batch])
        fixes += sum(r.fingerprint_fixes for r in outcome.reports.values())
        receipt = next(live)
        offline = outcome.estimates.get(batch.device_id)
        if offline is None:
            assert receipt.estimate is None or not batch.steps
            continue
        assert receipt.estimate is not None
        assert receipt.estimate.position.x_m == pytest.approx(offline.x, abs=1e-9)
        assert receipt.estimate.position.y_m == pytest.approx(offline.y, abs=1e-9)
        compared += 1
    assert compared > 100
    assert fixes > 0  # the crowd's fingerprint fixes (on by default) are part of what live and offline share
    assert f'crowdslam_fingerprint_fixes_total{{building="sim"}} {float(fixes)}' in metrics
    assert float(np.median(report.error_m)) < 2.0
    kinds = {m["type"] for m in received}
    assert "position" in kinds
    assert "anchor" in kinds
    positions = [m for m in received if m["type"] == "position"]
    assert len(positions) >= compared
    # the batched socket carries the same messages in the same order, several per frame
    assert {f["type"] for f in batched} == {"batch"}
    assert [m for f in batched for m in f["messages"]] == received  # type: ignore[attr-defined]
    assert len(batched) < len(received)
