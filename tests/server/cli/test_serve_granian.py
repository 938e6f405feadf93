"""``CROWDSLAM_HTTP_SERVER=granian``: the same app under granian's HTTP stack answers exactly as under
uvicorn (the same receipts for the same batches, the same Problem for a bad one, the batch stream over a
WebSocket), and stops cleanly on SIGTERM."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import httpx
import pytest

from server.cli.background_server import CLI, free_port, serve_process
from server.simulation.crowd_client import device_keys, prepare_building
from server.simulation.phones import simulated_batches
from slam_core.sim.simulation import Scenario, simulate
from tests.conftest import TESTBED

pytest.importorskip("granian")


def _served(tmp_path: Path, http_server: str) -> tuple[list[str], int, str, str, int]:
    """A fresh server under ``http_server``: every receipt of a small crowd's batches (as JSON), the status
    and Problem type of a malformed batch, the receipt of a batch streamed over the WebSocket, and the
    server's exit code on SIGTERM."""
    data = tmp_path / http_server
    env = {
        **os.environ,
        "CROWDSLAM_DATA_DIR": str(data),
        "CROWDSLAM_HTTP_SERVER": http_server,
        "CROWDSLAM_BUILDING_PROCESSES": "true",
    }
    subprocess.run([*CLI, "migrate"], env=env, check=True, capture_output=True)
    created = subprocess.run(
        [*CLI, "keys", "create", "--scope", "operator"], env=env, check=True, capture_output=True, text=True
    )
    operator = created.stdout.strip().splitlines()[-1]
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = 2
    raw["users"]["walk_length_m"] = 25.0
    sim = simulate(Scenario.from_dict(raw), 2)
    batches = list(simulated_batches(sim, "hq"))
    port = free_port()
    server = serve_process(env, port, data / "server.log")
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as client:
            prepare_building(client, "hq", operator, sim)
            keys = device_keys(client, "hq", operator, len(sim.users))
            receipts = []
            for batch in batches[:-1]:
                response = client.post(
                    "/v1/buildings/hq/batches",
                    content=batch.model_dump_json(exclude_none=True),
                    headers={"Authorization": f"Bearer {keys[batch.device_id]}"},
                )
                assert response.status_code == 200, response.text
                receipts.append(response.text)
            last = batches[-1]
            bad = client.post(
                "/v1/buildings/hq/batches",
                content=b'{"building_id": "hq"}',
                headers={"Authorization": f"Bearer {keys[last.device_id]}"},
            )
        streamed = _stream(port, keys[last.device_id], last.model_dump_json(exclude_none=True))
    finally:
        server.send_signal(signal.SIGTERM)
        code = server.wait(timeout=120)
    return receipts, bad.status_code, bad.json()["type"], streamed, code


def _stream(port: int, key: str, body: str) -> str:
    import websockets.sync.client

    url = f"ws://127.0.0.1:{port}/v1/buildings/hq/stream?token={key}"
    with websockets.sync.client.connect(url, open_timeout=30) as socket:
        socket.send(body)
        answer = socket.recv(timeout=30)
    return answer if isinstance(answer, str) else answer.decode()


def test_granian_serves_the_api_as_uvicorn_does(tmp_path: Path) -> None:
    under_uvicorn = _served(tmp_path, "uvicorn")
    under_granian = _served(tmp_path, "granian")
    receipts, status, problem, streamed, code = under_granian
    assert len(receipts) > 10
    assert any(json.loads(r)["estimate"] is not None for r in receipts)
    assert (status, problem, code) == (422, under_uvicorn[2], 0)
    assert json.loads(streamed)["status"] == "applied"
    # the same batches to the same building, one after another's receipt: the same receipts, byte for byte
    assert receipts == under_uvicorn[0]
    assert streamed == under_uvicorn[3]


def test_granian_without_the_package_says_how_to_install_it(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CROWDSLAM_")}
    env |= {"CROWDSLAM_DATA_DIR": str(tmp_path), "CROWDSLAM_HTTP_SERVER": "granian"}
    # a path entry whose finder says there is no granian, as on a machine without the extra
    stub = tmp_path / "stub"
    stub.mkdir()
    (stub / "sitecustomize.py").write_text(
        "import sys\n"
        "class NoGranian:\n"
        "    @staticmethod\n"
        "    def find_spec(name, path=None, target=None):\n"
        "        if name == 'granian' or name.startswith('granian.'):\n"
        "            raise ModuleNotFoundError(name)\n"
        "sys.meta_path.insert(0, NoGranian)\n"
    )
    env["PYTHONPATH"] = os.pathsep.join([str(stub), *filter(None, [os.environ.get("PYTHONPATH")])])
    done = subprocess.run(
        [*CLI, "serve", "--port", str(free_port())], env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 1
    assert "pip install 'crowdslam[granian]'" in done.stderr
