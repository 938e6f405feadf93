"""A batch changes the building only if its transaction commits. A batch whose tracker call fails after it
changed the tracker (a filter gone non-finite, a refused input, a database error) leaves no trace: the
building loads again from SQL, the other users of its group are applied, the failing batch alone is refused,
and neither the filters, the batch log nor the recording keep anything of it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
import pytest

from server.buildings.submissions import Submission
from server.errors import BatchFailedError, ProblemError
from server.ingestion import transport
from server.recordings.recorder import BuildingRecorder, read_batches
from slam_core.tracking import tracker as tracker_module
from tests.server.api.test_api import _batch
from tests.server.buildings.test_restart import (
    CROWD,
    _building,
    _estimates,
    _fresh_building,
    _groups,
    _pin_known,
)
from tests.server.conftest import Api

GROUPS = _groups(CROWD, size=5)
POISON = 3  # the group in which one user's batch fails


def _poisoned(monkeypatch: pytest.MonkeyPatch, sub: Submission, exc: Exception) -> None:
    """The tracker call holding this batch fails after it has changed the tracker."""
    real = tracker_module.BuildingTracker.apply
    step_t = transport.unpack(sub.columns).step_t
    assert step_t.size
    device, first_step = sub.header.device_id, int(step_t[0])

    def apply(self: tracker_module.BuildingTracker, batches: list[tracker_module.UserBatch]) -> object:
        outcome = real(self, batches)
        if any(b.user == device and b.step_t.size and b.step_t[0] == first_step for b in batches):
            raise exc
        return outcome

    monkeypatch.setattr(tracker_module.BuildingTracker, "apply", apply)


def _status(receipt: object) -> str:
    return "problem" if isinstance(receipt, ProblemError) else str(getattr(receipt, "status", ""))


@pytest.mark.parametrize("failure", [ValueError("not finite"), RuntimeError("a bug")])
def test_a_failing_batch_leaves_no_trace_and_fails_alone(
    database_url: str, sqlite_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: Exception
) -> None:
    group = GROUPS[POISON]
    liar = group[-1]  # its device's last batch in the group: re-sent, it is not behind a later one
    # the reference never sees the failing batch
    reference = _building(_fresh_building(sqlite_url.replace(".sqlite3", "-ref.sqlite3")))
    _pin_known(reference)
    for g in GROUPS[:POISON]:
        reference.process(g)
    reference.process(group[:-1])

    engine = _fresh_building(database_url)
    building = _building(engine)
    building.building.recorder = BuildingRecorder(tmp_path / "recordings", "hq")
    _pin_known(building)
    for g in GROUPS[:POISON]:
        building.process(g)
    with monkeypatch.context() as m:
        _poisoned(m, liar, failure)
        receipts = building.process(group).receipts
    assert [_status(r) for r in receipts[:-1]] == ["applied"] * (len(group) - 1)
    refused = receipts[-1]
    # an error inside the building is the server's: 500, without the exception's text
    assert isinstance(refused, BatchFailedError)
    assert refused.status == 500
    assert str(failure) not in refused.detail
    assert building.counters.failed_batches == 1
    assert building.counters.reloads == 2  # the group's, then the failing batch's own
    assert _estimates(building) == _estimates(reference)  # bit for bit: nothing of the failed call kept
    # nor of its counts: the metrics count what committed
    for name in ("batches", "estimates", "encounters", "steps_dropped", "duplicates", "late", "snapshots"):
        assert getattr(building.counters, name) == getattr(reference.counters, name), name

    # the failed batch is not in the log (a retry applies it now) nor in the recording
    retry = building.process([liar]).receipts[0]
    assert _status(retry) == "applied"
    building.recorder.close()
    files = sorted((tmp_path / "recordings").rglob("*.mcap"))
    recorded = [json.loads(r.raw)["batch_id"] for f in files for r in read_batches(f)]
    assert recorded.count(liar.header.batch_id) == 1
    assert len(recorded) == sum(len(g) for g in GROUPS[: POISON + 1])

    # and tracking goes on for everyone
    for g in GROUPS[POISON + 1 :]:
        assert all(_status(r) in ("applied", "late") for r in building.process(g).receipts)


def test_a_restart_after_a_failed_group_restores_the_committed_state(
    sqlite_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    engine = _fresh_building(sqlite_url)
    building = _building(engine)
    _pin_known(building)
    for g in GROUPS[:POISON]:
        building.process(g)
    with monkeypatch.context() as m:
        _poisoned(m, GROUPS[POISON][-1], ValueError("not finite"))
        building.process(GROUPS[POISON])
    kept = _estimates(building)
    del building  # as after kill -9
    restarted = _building(engine)
    assert _estimates(restarted) == kept


def test_through_the_api_the_failing_batch_is_refused_and_health_says_degraded(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Over HTTP: the batch whose tracker call fails answers 500 (the server's error, not the client's) and
    changes nothing, its user's next batch is applied, other phones are served throughout, and /healthz
    names the building as degraded."""
    api.create_building()
    keys = {d: api.key("hq", "device", d) for d in ("phone-1", "phone-2")}

    def post(body: dict[str, Any]) -> httpx.Response:
        return api.client.post(
            "/v1/buildings/hq/batches", json=body, headers=api.auth(keys[body["device_id"]])
        )

    for seq in range(3):
        for device in keys:
            response = post(_batch(seq, device))
            assert response.json()["status"] == "applied", response.text
    assert api.client.get("/healthz").json()["status"] == "ok"
    poisoned = _batch(3, "phone-1")
    first_step = poisoned["steps"][0]["t_ms"]
    with monkeypatch.context() as m:
        real = tracker_module.BuildingTracker.apply

        def apply(self: tracker_module.BuildingTracker, batches: list[tracker_module.UserBatch]) -> object:
            outcome = real(self, batches)
            if any(b.user == "phone-1" and b.step_t.size and b.step_t[0] == first_step for b in batches):
                raise ValueError("the filter's estimate is not finite")
            return outcome

        m.setattr(tracker_module.BuildingTracker, "apply", apply)
        refused = post(poisoned)
        assert refused.status_code == 500, refused.text
        assert refused.headers["content-type"] == "application/problem+json"
        assert "could not apply" in refused.json()["detail"]
        assert "not finite" not in refused.text
        assert post(_batch(3, "phone-2")).json()["status"] == "applied"
    health = api.client.get("/healthz").json()
    assert health["status"] == "degraded"
    assert health["failing_buildings"][0]["building_id"] == "hq"
    assert health["failing_buildings"][0]["failed_batches"] == 1
    # the refused batch was not applied: re-sent, it is (its id was never stored), and the user goes on
    again = post(poisoned)
    assert again.json()["status"] == "applied", again.text
    assert post(_batch(4, "phone-1")).json()["status"] == "applied"
