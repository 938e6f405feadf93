"""An error inside a building is the server's, not the client's: a building that cannot be loaded answers 503
(with ``Retry-After``, without the error's text), is named in ``/healthz`` and the metrics, and is tried again
after ``LOAD_RETRY_S``; a logged batch that cannot be applied again on load is counted and the building comes
back without it instead of not at all."""

from __future__ import annotations

import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.buildings import recovery as recovery_module
from server.buildings import registry as registry_module
from server.ingestion import transport
from server.settings import Settings
from server.store.db import make_engine, make_session_factory
from server.store.models import FloorPlanRow
from slam_core.tracking import tracker as tracker_module
from tests.server.api.test_api import _batch
from tests.server.buildings.test_restart import CROWD, _building, _estimates, _fresh_building, _groups
from tests.server.conftest import Api, migrate_with_operator

SECRET = "the text of an error inside the building"


def _post(api: Api, key: str, seq: int) -> httpx.Response:
    return api.client.post("/v1/buildings/hq/batches", json=_batch(seq, "phone-1"), headers=api.auth(key))


def test_a_building_that_cannot_load_answers_503_and_is_named_until_it_loads(
    sqlite_api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    api = sqlite_api
    api.create_building()
    key = api.key("hq", "device", "phone-1")
    real_load = recovery_module.Recovery.load
    attempts = []

    def failing_load(self: recovery_module.Recovery) -> Any:
        attempts.append(1)
        raise RuntimeError(SECRET)

    monkeypatch.setattr(recovery_module.Recovery, "load", failing_load)
    monkeypatch.setattr(registry_module, "LOAD_RETRY_S", 1.0)
    refused = _post(api, key, 0)
    assert refused.status_code == 503, refused.text
    assert refused.headers["content-type"] == "application/problem+json"
    assert float(refused.headers["retry-after"]) > 0
    assert SECRET not in refused.text
    assert "cannot be loaded" in refused.json()["detail"]
    health = api.client.get("/healthz").json()
    assert health["status"] == "degraded"
    assert [(f["building_id"], f["failed_loads"]) for f in health["failing_buildings"]] == [("hq", 1)]
    metrics = api.client.get("/metrics").text
    assert 'crowdslam_building_failing{building="hq"} 1.0' in metrics
    assert 'crowdslam_building_load_failures{building="hq"} 1.0' in metrics
    # until Retry-After, a request costs nothing: the building is not loaded again
    assert _post(api, key, 0).status_code == 503
    assert len(attempts) == 1

    time.sleep(1.0)
    refused = _post(api, key, 0)  # tried again after Retry-After (still failing)
    assert refused.status_code == 503
    assert len(attempts) == 2
    assert api.client.get("/healthz").json()["failing_buildings"][0]["failed_loads"] == 2

    monkeypatch.setattr(recovery_module.Recovery, "load", real_load)
    time.sleep(1.0)
    applied = _post(api, key, 0)
    assert applied.status_code == 200, applied.text
    assert applied.json()["status"] == "applied"
    health = api.client.get("/healthz").json()
    assert health["status"] == "ok"
    assert health["failing_buildings"] == []
    assert 'crowdslam_building_failing{building="hq"}' not in api.client.get("/metrics").text


def test_a_building_process_that_cannot_load_answers_503(sqlite_url: str, tmp_path: Path) -> None:
    """In a process of its own: a floor plan in SQL that no longer reads (written by hand, say) fails the
    building's load there; the front answers 503 and names it, and serves the other buildings."""
    operator = migrate_with_operator(sqlite_url)
    settings = Settings(data_dir=tmp_path / "data", database_url=sqlite_url, building_processes=True)
    with TestClient(create_app(settings)) as client:
        api = Api(client, operator, sqlite_url, settings)
        for building in ("hq", "annex"):
            body = {"id": building, "name": building, "floors": [{"level": 0, "name": "G"}]}
            assert client.post("/v1/buildings", json=body, headers=api.auth(operator)).status_code == 201
        key = api.key("hq", "device", "phone-1")
        first = client.post("/v1/buildings/hq/batches", json=_batch(0, "phone-1"), headers=api.auth(key))
        assert first.status_code == 200, first.text
        engine = make_engine(sqlite_url)
        with make_session_factory(engine).begin() as session:
            session.add(
                FloorPlanRow(building_id="hq", level=0, geojson="{not json", updated_at=datetime.now(UTC))
            )
        engine.dispose()
        # its process loaded before the plan was broken; started again, it reads the broken plan
        handle = client.app.state.crowdslam.tracking.handles["hq"]
        handle._process.kill()
        handle._process.join()
        deadline = time.monotonic() + 10.0
        while handle.alive and time.monotonic() < deadline:  # the front has seen its socket close
            time.sleep(0.01)
        refused = client.post("/v1/buildings/hq/batches", json=_batch(1, "phone-1"), headers=api.auth(key))
        assert refused.status_code == 503, refused.text
        assert "cannot be loaded" in refused.json()["detail"]
        failing = client.get("/healthz").json()["failing_buildings"]
        assert [f["building_id"] for f in failing] == ["hq"]
        other = api.key("annex", "device", "phone-1")
        body = {**_batch(0, "phone-1"), "building_id": "annex"}
        served = client.post("/v1/buildings/annex/batches", json=body, headers=api.auth(other))
        assert served.status_code == 200, served.text


def test_a_logged_batch_that_cannot_be_replayed_is_counted_and_the_building_comes_back(
    sqlite_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    groups = _groups(CROWD)[:6]
    engine = _fresh_building(sqlite_url)
    building = _building(engine)
    for group in groups:
        building.process(group)
    poisoned = groups[3][0]
    first_step = int(transport.unpack(poisoned.columns).step_t[0])
    real_apply = tracker_module.BuildingTracker.apply

    def apply(self: tracker_module.BuildingTracker, batches: list[tracker_module.UserBatch]) -> Any:
        if any(b.user == poisoned.header.effective_user_id and b.step_t.size for b in batches) and any(
            b.step_t.size and int(b.step_t[0]) == first_step for b in batches
        ):
            raise ValueError(SECRET)
        return real_apply(self, batches)

    del building  # as after kill -9
    with monkeypatch.context() as m:
        m.setattr(tracker_module.BuildingTracker, "apply", apply)
        restarted = _building(engine)
    failed = restarted.counters.replay_failures  # the batches of the tracker call that held it
    assert 1 <= failed <= len(groups[3])
    assert restarted.counters.replayed == sum(len(g) for g in groups) - failed
    assert restarted.counters.last_failure_unix_s > 0
    receipts = restarted.process(_groups(CROWD)[6]).receipts
    assert all(getattr(r, "status", None) == "applied" for r in receipts)
    assert _estimates(restarted)
    engine.dispose()
