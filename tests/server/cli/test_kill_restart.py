"""``kill -9`` of a real server process: after a restart the anchor map is intact, every acknowledged batch
is still applied (a retry is a duplicate) and tracking resumes where it stopped."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import httpx
import pytest

from schemas.api import BatchReceipt
from server.cli.background_server import (
    free_port,
    migrate_with_operator_key,
    serve_process,
    spawned_processes,
)
from server.simulation.crowd_client import device_keys, prepare_building
from server.simulation.phones import simulated_batches
from slam_core.sim.simulation import Scenario, simulate
from tests.conftest import TESTBED
from tests.server.signal_maps.test_jobs import _walk


@pytest.mark.parametrize("processes", [False, True], ids=["building-threads", "building-processes"])
def test_kill_9_loses_no_acknowledged_batch_and_tracking_resumes(tmp_path: Path, processes: bool) -> None:
    env = {
        **os.environ,
        "CROWDSLAM_DATA_DIR": str(tmp_path),
        "CROWDSLAM_SNAPSHOT_PERIOD_S": "1e9",
        "CROWDSLAM_BUILDING_PROCESSES": str(processes).lower(),
    }
    operator = migrate_with_operator_key(env)
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = 3
    raw["users"]["walk_length_m"] = 40.0
    sim = simulate(Scenario.from_dict(raw), 4)
    batches = list(simulated_batches(sim, "hq"))
    cut = len(batches) // 2

    port = free_port()

    def post(client: httpx.Client, keys: dict[str, str], batch_index: int) -> BatchReceipt:
        batch = batches[batch_index]
        response = client.post(
            "/v1/buildings/hq/batches",
            content=batch.model_dump_json(exclude_none=True),
            headers={"Authorization": f"Bearer {keys[batch.device_id]}", "Content-Type": "application/json"},
        )
        assert response.status_code == 200, response.text
        return BatchReceipt.model_validate_json(response.content)

    server = serve_process(env, port, tmp_path / "server.log")
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as client:
            prepare_building(client, "hq", operator, sim)
            keys = device_keys(client, "hq", operator, len(sim.users))
            before = [post(client, keys, i) for i in range(cut)]
            auth = {"Authorization": f"Bearer {operator}"}
            anchors_before = client.get("/v1/buildings/hq/anchors", headers=auth).json()
            positions_before = client.get("/v1/buildings/hq/positions", headers=auth).json()
            assert (len(spawned_processes(tmp_path)) == 1) == processes
    finally:
        server.send_signal(signal.SIGKILL)
        server.wait()
    assert all(r.status == "applied" for r in before)
    deadline = time.monotonic() + 10.0  # a building's process dies with the server
    while spawned_processes(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert spawned_processes(tmp_path) == []

    server = serve_process(env, port, tmp_path / "server.log")
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as client:
            auth = {"Authorization": f"Bearer {operator}"}
            assert client.get("/v1/buildings/hq/anchors", headers=auth).json() == anchors_before
            assert client.get("/v1/buildings/hq/positions", headers=auth).json() == positions_before
            retried = post(client, keys, cut - 1)
            assert retried.duplicate
            after = [post(client, keys, i) for i in range(cut, len(batches))]
            metrics = client.get("/metrics").text
            positions_at_stop = client.get("/v1/buildings/hq/positions", headers=auth).json()
    finally:
        server.send_signal(signal.SIGTERM)  # as `docker stop` does to the image's `crowdslam serve`
        server.wait(timeout=60)  # uvicorn shuts down, then exits by the signal it caught (-15)
    assert all(r.status == "applied" for r in after)
    # every user the crash interrupted is still tracked: no new start fix was needed
    tracked_before = {r.estimate.user_id for r in before if r.estimate is not None}
    assert tracked_before
    resumed = [r for r in after if r.estimate is not None and r.estimate.user_id in tracked_before]
    assert resumed
    assert all(r.tracking for r in resumed)
    assert f'crowdslam_replayed_total{{building="hq"}} {float(cut)}' in metrics
    # SIGTERM stopped it cleanly: its last snapshot covers every batch, so the next start replays none
    server = serve_process(env, port, tmp_path / "server.log")
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as client:
            auth = {"Authorization": f"Bearer {operator}"}
            assert client.get("/v1/buildings/hq/positions", headers=auth).json() == positions_at_stop
            assert client.get("/v1/buildings/hq/anchors", headers=auth).status_code == 200  # loads it
            assert 'crowdslam_replayed_total{building="hq"} 0.0' in client.get("/metrics").text
    finally:
        server.send_signal(signal.SIGKILL)
        server.wait()


def test_kill_9_leaves_no_signal_map_build_behind(tmp_path: Path) -> None:
    """A signal-map build's process had been orphaned by ``kill -9`` of the server, holding a core for a job
    nobody would read. It dies with the server."""
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(tmp_path)}
    auth = {"Authorization": f"Bearer {migrate_with_operator_key(env)}"}
    port = free_port()
    server = serve_process(env, port, tmp_path / "server.log")
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as client:
            assert (
                client.post("/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=auth).status_code == 201
            )
            minted = client.post(
                "/v1/buildings/hq/keys", json={"scope": "device", "device_id": "a"}, headers=auth
            )
            device = {"Authorization": f"Bearer {minted.json()['key']}"}
            for body in _walk("a", 0.0, 28.0, 20):
                assert client.post("/v1/buildings/hq/batches", json=body, headers=device).status_code == 200
            job = client.post("/v1/buildings/hq/signal-maps", headers=auth).json()
            deadline = time.monotonic() + 120.0
            while (
                client.get(f"/v1/buildings/hq/signal-maps/{job['id']}", headers=auth).json()["status"]
                == "queued"
            ):
                assert time.monotonic() < deadline, "the build never started"
                time.sleep(0.02)
            builders = spawned_processes(tmp_path)  # the build's process, spawned by the server
            assert builders
    finally:
        server.send_signal(signal.SIGKILL)
        server.wait()
    deadline = time.monotonic() + 10.0
    while spawned_processes(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert spawned_processes(tmp_path) == [], "a build's process outlived the server"
