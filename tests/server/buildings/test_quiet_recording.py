"""A building that goes quiet writes its recording's last chunk within ``IDLE_S``, in a thread or a process
of its own (the chunk would otherwise wait for the next batch, lost in a crash meanwhile), and a signal-map
build started at once reads every batch recorded."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.buildings import handles
from server.buildings.host import IDLE_S
from server.recordings.recorder import read_batches
from server.settings import Settings
from tests.server.api.test_api import _batch
from tests.server.conftest import migrate_with_operator


def _recorded(root: Path) -> list[str]:
    return [json.loads(r.raw)["batch_id"] for f in sorted(root.rglob("*.mcap")) for r in read_batches(f)]


@pytest.mark.parametrize("processes", [False, True], ids=["thread", "process"])
def test_a_quiet_building_writes_its_last_chunk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, processes: bool
) -> None:
    monkeypatch.setattr(handles, "IDLE_S", 0.3)  # the thread's; a process has its own (``IDLE_S``)
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, building_processes=processes)
    with TestClient(create_app(settings)) as client:
        auth = {"Authorization": f"Bearer {operator}"}
        assert client.post("/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=auth).status_code == 201
        created = client.post(
            "/v1/buildings/hq/keys", json={"scope": "device", "device_id": "phone-1"}, headers=auth
        )
        device = {"Authorization": f"Bearer {created.json()['key']}"}
        for seq in range(3):
            assert (
                client.post("/v1/buildings/hq/batches", json=_batch(seq), headers=device).status_code == 200
            )
        assert _recorded(settings.recordings_dir) == []  # in the chunk in progress
        deadline = time.monotonic() + (1.0 if not processes else IDLE_S + 10.0)
        while not _recorded(settings.recordings_dir) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _recorded(settings.recordings_dir) == [_batch(seq)["batch_id"] for seq in range(3)]


def test_a_signal_map_build_reads_what_was_recorded_a_moment_ago(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, building_processes=False)
    with TestClient(create_app(settings)) as client:
        auth = {"Authorization": f"Bearer {operator}"}
        client.post("/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=auth)
        created = client.post(
            "/v1/buildings/hq/keys", json={"scope": "device", "device_id": "phone-1"}, headers=auth
        )
        device = {"Authorization": f"Bearer {created.json()['key']}"}
        assert client.post("/v1/buildings/hq/batches", json=_batch(0), headers=device).status_code == 200
        started = client.post("/v1/buildings/hq/signal-maps", headers=auth)
        assert started.status_code == 202, started.text
        assert _recorded(settings.recordings_dir) == [_batch(0)["batch_id"]]  # flushed before the build
