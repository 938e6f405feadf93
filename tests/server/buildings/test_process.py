"""Buildings in processes of their own (``CROWDSLAM_BUILDING_PROCESSES``): the API answers as with
in-process buildings (the end-to-end test compares live estimates with the offline engine in both modes);
an unknown building never starts a process; a building process that dies fails its waiting requests with
503 and is started again on the next request, restored from its snapshot and batch log; a clean shutdown
snapshots it; the front compiles the kernels into numba's cache once, in a child, before it serves."""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app import create_app
from server.settings import Settings
from server.slam import warmup
from server.store.db import make_engine, make_session_factory
from server.store.models import BatchLogRow, TrackerSnapshotRow
from tests.server.api.test_api import _batch
from tests.server.conftest import Api, migrate_with_operator


@pytest.fixture
def process_api(tmp_path: Path) -> Iterator[Api]:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, building_processes=True)
    with TestClient(create_app(settings)) as client:
        yield Api(client, operator, url, settings)


def _logged_and_snapshots(url: str) -> tuple[int, int]:
    engine = make_engine(url)
    with make_session_factory(engine)() as session:
        logged = session.execute(select(func.count()).select_from(BatchLogRow)).scalar_one()
        snapshots = session.execute(select(func.count()).select_from(TrackerSnapshotRow)).scalar_one()
    engine.dispose()
    return int(logged), int(snapshots)


def test_a_building_process_serves_batches_anchors_and_metrics(process_api: Api) -> None:
    api = process_api
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    dashboard = api.key("hq", "dashboard")
    for seq in range(4):
        r = api.client.post("/v1/buildings/hq/batches", json=_batch(seq), headers=api.auth(device))
        assert r.status_code == 200, r.text
        assert r.json()["status"] == "applied"
    assert (
        api.client.post("/v1/buildings/hq/batches", json=_batch(3), headers=api.auth(device)).json()["status"]
        == "duplicate"
    )
    late = api.client.post(
        "/v1/buildings/hq/batches", json=_batch(2) | {"batch_id": "again"}, headers=api.auth(device)
    )
    assert late.json()["status"] == "late"
    put = api.client.put(
        "/v1/buildings/hq/anchors/door",
        json={"type": "door", "position": {"x_m": 1.0, "y_m": 2.0}},
        headers=api.auth(api.operator),
    )
    assert put.status_code == 200, put.text
    anchors = api.client.get("/v1/buildings/hq/anchors", headers=api.auth(dashboard)).json()
    assert [a["id"] for a in anchors] == ["door"]
    missing = api.client.get("/v1/buildings/hq/anchors/nowhere", headers=api.auth(dashboard))
    assert missing.status_code == 404  # a ProblemError raised in the building's process
    positions = api.client.get("/v1/buildings/hq/positions", headers=api.auth(dashboard)).json()
    assert [p["user_id"] for p in positions] == ["phone-1"]
    metrics = api.client.get("/metrics").text
    assert 'crowdslam_batches_total{building="hq"} 6.0' in metrics
    assert 'crowdslam_duplicates_total{building="hq"} 1.0' in metrics


def test_an_unknown_building_starts_no_process(process_api: Api) -> None:
    api = process_api
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    r = api.client.get("/v1/buildings/elsewhere/anchors", headers=api.auth(api.operator))
    assert r.status_code == 404
    assert api.client.app.state.crowdslam.tracking.handles == {}  # type: ignore[attr-defined]
    assert (
        api.client.post("/v1/buildings/hq/batches", json=_batch(0), headers=api.auth(device)).status_code
        == 200
    )


def test_a_dead_building_process_is_started_again_from_its_snapshot_and_log(process_api: Api) -> None:
    api = process_api
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    for seq in range(3):
        assert (
            api.client.post("/v1/buildings/hq/batches", json=_batch(seq), headers=api.auth(device)).json()[
                "status"
            ]
            == "applied"
        )
    tracking = api.client.app.state.crowdslam.tracking  # type: ignore[attr-defined]
    first = tracking.handles["hq"]
    os.kill(first.pid, signal.SIGKILL)
    deadline = time.monotonic() + 30
    while first.alive and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not first.alive
    # the retry of an acknowledged batch is still a duplicate: the new process replayed the log
    retry = api.client.post("/v1/buildings/hq/batches", json=_batch(2), headers=api.auth(device))
    assert retry.status_code == 200, retry.text
    assert retry.json()["status"] == "duplicate"
    assert tracking.handles["hq"] is not first
    nxt = api.client.post("/v1/buildings/hq/batches", json=_batch(3), headers=api.auth(device)).json()
    assert nxt["status"] == "applied"
    assert nxt["tracking"] is True  # the filter came back: no new fix needed
    metrics = api.client.get("/metrics").text
    assert 'crowdslam_replayed_total{building="hq"} 3.0' in metrics


def test_a_clean_shutdown_snapshots_every_building_process(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, building_processes=True)
    with TestClient(create_app(settings)) as client:
        api = Api(client, operator, url, settings)
        api.create_building()
        device = api.key("hq", "device", "phone-1")
        for seq in range(3):
            client.post("/v1/buildings/hq/batches", json=_batch(seq), headers=api.auth(device))
        assert _logged_and_snapshots(url)[0] == 3  # acknowledged, not yet covered by a snapshot
        worker = client.app.state.crowdslam.tracking.handles["hq"]  # type: ignore[attr-defined]
    assert _logged_and_snapshots(url) == (0, 1)
    assert not worker._process.is_alive()


def test_the_kernels_are_compiled_once_in_a_child_before_the_server_takes_requests(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A first start runs the warm-up in a child, and marks the cache warm for this CPU; a later start finds
    the mark and spends no child on it (~2 s a start)."""
    marker = tmp_path / "warm-cpu"
    monkeypatch.setattr(warmup, "warm_marker", lambda: marker)
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, building_processes=True)
    for start, said in enumerate(("kernels compiled into the cache in", "kernels found in the cache")):
        caplog.clear()
        with (
            caplog.at_level(logging.INFO, logger="server.slam.warmup"),
            TestClient(create_app(settings)) as client,
        ):
            assert client.get("/healthz").status_code == 200
            assert any(r.getMessage().startswith(said) for r in caplog.records), start
            assert client.app.state.crowdslam.tracking.handles == {}  # type: ignore[attr-defined]
        assert marker.exists()


def _exit_three(settings: Settings, steps: object, parent_pid: int | None = None) -> None:
    raise SystemExit(3)


def test_a_server_whose_kernels_fail_to_compile_does_not_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    migrate_with_operator(url)
    monkeypatch.setattr(warmup, "warm_kernels_for", _exit_three)  # what the child runs
    monkeypatch.setattr(warmup, "warm_marker", lambda: tmp_path / "warm-cpu")  # not marked warm yet
    before = set(_checkpoint_threads())
    settings = Settings(data_dir=tmp_path, database_url=url, building_processes=True)
    with (
        pytest.raises(RuntimeError, match=r"compiling the kernels failed .*exit code 3"),
        TestClient(create_app(settings)),
    ):
        pass
    deadline = time.monotonic() + 10  # the database engine was disposed, its checkpoint thread with it
    while set(_checkpoint_threads()) - before and time.monotonic() < deadline:
        time.sleep(0.05)
    assert set(_checkpoint_threads()) - before == set()


def _checkpoint_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "sqlite-checkpoints"]
