"""After every attack of the hostile-client suite, run one after another against a building while two honest
phones post, the building is what it would have been without them: the honest users' positions and the
crowd map equal those of a building that never saw the attacks, the batch log and the recording hold the
honest batches only, and the recording replays offline without error. On SQLite and PostgreSQL."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from server.recordings.recorder import read_batches
from server.replay import replay_offline
from server.store.db import make_engine, make_session_factory
from server.store.models import BatchRow
from slam_core.tracking import tracker as tracker_module
from tests.server.api.test_api import _batch
from tests.server.conftest import Api, make_api

HONEST = ("phone-1", "phone-2")
ROUNDS = 14  # at least one round per attack


def _serve(url: str, factory: pytest.TempPathFactory) -> contextlib.AbstractContextManager[Api]:
    return contextlib.contextmanager(make_api)(url, factory)


def _setup(api: Api) -> dict[str, str]:
    api.create_building(size_m=(60.0, 50.0))
    pinned = api.client.put(
        "/v1/buildings/hq/anchors/entrance",
        json={"type": "door", "position": {"x_m": 5.0, "y_m": 12.0}},
        headers=api.auth(api.operator),
    )
    assert pinned.status_code == 200, pinned.text
    keys = {d: api.key("hq", "device", d) for d in (*HONEST, "phone-3")}
    keys["dashboard"] = api.key("hq", "dashboard")
    return keys


def _honest(seq: int, device: str) -> dict[str, Any]:
    body = _batch(seq, device)
    if seq == 6:  # the phone passes the entrance: a known-anchor reading
        body["landmarks"] = [{"kind": "anchor", "t_ms": body["steps"][0]["t_ms"], "anchor_id": "entrance"}]
    return body


def _post(api: Api, key: str | None, body: Any, **kwargs: Any) -> httpx.Response:
    headers = {} if key is None else api.auth(key)
    if isinstance(body, bytes):
        return api.client.post("/v1/buildings/hq/batches", content=body, headers=headers, **kwargs)
    return api.client.post("/v1/buildings/hq/batches", json=body, headers=headers, **kwargs)


def _attacks(api: Api, keys: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> list[Callable[[int], int]]:
    """Each attack, given the round it runs in, returns the status the server answered; all are refused."""
    attacker = keys["phone-3"]

    def t(seq: int) -> int:
        return int(_batch(seq)["steps"][0]["t_ms"])

    def absurd_fix(seq: int) -> int:
        fix = {"kind": "fix", "t_ms": t(seq), "position": {"x_m": 1e160, "y_m": 0.0}}
        return _post(api, attacker, _batch(seq, "phone-3", landmarks=[fix])).status_code

    def outside_the_building(seq: int) -> int:
        fix = {"kind": "fix", "t_ms": t(seq), "position": {"x_m": 2000.0, "y_m": 0.0}}
        return _post(api, attacker, _batch(seq, "phone-3", landmarks=[fix])).status_code

    def impersonation(seq: int) -> int:
        fix = {"kind": "fix", "t_ms": t(seq), "position": {"x_m": 55.0, "y_m": 5.0}}
        teleport = _batch(seq, "phone-3", user_id="phone-2", landmarks=[fix])
        return _post(api, attacker, teleport).status_code

    def another_devices_batch(seq: int) -> int:
        return _post(api, attacker, _batch(seq, "phone-1")).status_code

    def from_the_future(seq: int) -> int:
        body = _batch(seq, "phone-3")
        for step in body["steps"]:
            step["t_ms"] = 4_070_908_800_000 + step["t_ms"] % 10_000
        return _post(api, attacker, body).status_code

    def deep_json(seq: int) -> int:
        return _post(api, attacker, b"[" * 5000 + b"]" * 5000).status_code

    def garbage(seq: int) -> int:
        return _post(api, attacker, b"\xff\xfe not json").status_code

    def anonymous_huge_body(seq: int) -> int:
        return _post(api, None, b"x" * (api.settings.max_batch_bytes + 1)).status_code

    def wrong_building(seq: int) -> int:
        return _post(api, attacker, _batch(seq, "phone-3", building_id="elsewhere")).status_code

    def dashboard_pins_an_anchor(seq: int) -> int:
        body = {"type": "door", "position": {"x_m": 1.0, "y_m": 1.0}}
        headers = api.auth(keys["dashboard"])
        return api.client.put("/v1/buildings/hq/anchors/x", json=body, headers=headers).status_code

    def device_deletes_the_entrance(seq: int) -> int:
        headers = api.auth(attacker)
        return api.client.delete("/v1/buildings/hq/anchors/entrance", headers=headers).status_code

    def anchor_at_1e308(seq: int) -> int:
        body = {"type": "door", "position": {"x_m": 1e308, "y_m": 0.0}}
        headers = api.auth(api.operator)
        return api.client.put("/v1/buildings/hq/anchors/far", json=body, headers=headers).status_code

    def engine_failure(seq: int) -> int:
        """A batch that passes every check but whose tracker call fails after changing the tracker."""
        real = tracker_module.BuildingTracker.apply

        def apply(self: tracker_module.BuildingTracker, batches: list[tracker_module.UserBatch]) -> object:
            outcome = real(self, batches)
            if any(b.user == "phone-3" for b in batches):
                raise ValueError("the filter's estimate is not finite")
            return outcome

        fix = {"kind": "fix", "t_ms": t(seq), "position": {"x_m": 30.0, "y_m": 20.0}}
        with monkeypatch.context() as m:
            m.setattr(tracker_module.BuildingTracker, "apply", apply)
            return _post(api, attacker, _batch(seq, "phone-3", landmarks=[fix])).status_code

    return [
        absurd_fix,
        outside_the_building,
        impersonation,
        another_devices_batch,
        from_the_future,
        deep_json,
        garbage,
        anonymous_huge_body,
        wrong_building,
        dashboard_pins_an_anchor,
        device_deletes_the_entrance,
        anchor_at_1e308,
        engine_failure,
    ]


def _state(api: Api) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The honest users' latest estimates and the crowd map, as the API gives them."""
    positions = api.client.get("/v1/buildings/hq/positions", headers=api.auth(api.operator)).json()
    anchors = api.client.get("/v1/buildings/hq/anchors", headers=api.auth(api.operator)).json()
    return sorted(positions, key=lambda e: e["user_id"]), anchors


def _logged_batch_ids(url: str) -> list[str]:
    engine = make_engine(url)
    try:
        with make_session_factory(engine)() as session:
            return sorted(session.execute(select(BatchRow.batch_id)).scalars())
    finally:
        engine.dispose()


@pytest.fixture
def control(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[list[Any], list[Any]]]:
    """The building with the honest phones only."""
    url = f"sqlite:///{tmp_path_factory.mktemp('control') / 'control.sqlite3'}"
    with _serve(url, tmp_path_factory) as api:
        keys = _setup(api)
        for seq in range(ROUNDS):
            for device in HONEST:
                assert _post(api, keys[device], _honest(seq, device)).json()["status"] == "applied"
        yield _state(api)


def test_every_attack_leaves_the_building_as_it_was(
    database_url: str,
    tmp_path_factory: pytest.TempPathFactory,
    monkeypatch: pytest.MonkeyPatch,
    control: tuple[list[Any], list[Any]],
) -> None:
    honest_ids: list[str] = []
    with _serve(database_url, tmp_path_factory) as api:
        keys = _setup(api)
        attacks = _attacks(api, keys, monkeypatch)
        assert len(attacks) <= ROUNDS
        answered: dict[str, int] = {}
        for seq in range(ROUNDS):
            for device in HONEST:
                body = _honest(seq, device)
                response = _post(api, keys[device], body)
                assert response.json()["status"] == "applied", response.text
                honest_ids.append(body["batch_id"])
                if seq % 3 == 1:  # a retry changes nothing
                    assert _post(api, keys[device], body).json()["status"] == "duplicate"
            attack = attacks[seq % len(attacks)]
            answered[attack.__name__] = attack(seq)
        assert set(answered) == {a.__name__ for a in attacks}
        # every attack is refused: the client's with a 4xx, the engine failure it set off (an error inside the
        # building) with the server's 500
        assert answered.pop("engine_failure") == 500
        assert all(400 <= code < 500 for code in answered.values()), answered
        assert _state(api) == control  # the honest users bit for bit, and the anchor map
        # nothing of the attacker's refused fixes was kept: its first plain batch finds it untracked
        plain = _batch(ROUNDS, "phone-3")
        receipt = _post(api, keys["phone-3"], plain).json()
        assert (receipt["status"], receipt["tracking"]) == ("applied", False), receipt
        honest_ids.append(plain["batch_id"])
        recordings = api.settings.recordings_dir
    assert _logged_batch_ids(database_url) == sorted(honest_ids)
    files = sorted(recordings.rglob("*.mcap"))
    recorded = [batch for f in files for batch in read_batches(f)]
    assert sorted(json.loads(r.raw)["batch_id"] for r in recorded) == sorted(honest_ids)
    report = replay_offline(recorded, api.settings)
    assert (report.rejected, report.applied) == (0, len(honest_ids))
    assert set(report.latest) == set(HONEST)  # the attacker was never tracked
