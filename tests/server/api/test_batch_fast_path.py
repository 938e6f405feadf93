"""POST /batches is served as pure ASGI before the app's middleware (``serve_batch``, taken by
``CrowdslamApp``); the documented FastAPI route must answer exactly as it does. The same requests go to two
apps on two databases, one without the fast path: statuses, bodies and the headers a client reads agree,
for a receipt and for every error."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from server.api import batches
from server.app import create_app
from server.settings import Settings
from tests.server.api.test_api import _batch
from tests.server.conftest import migrate_with_operator


def _client(tmp: Path, fast: bool) -> tuple[TestClient, str]:
    url = f"sqlite:///{tmp / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    app = create_app(Settings(data_dir=tmp, database_url=url, max_batch_bytes=4_000))
    app.batch_fast_path = fast
    return TestClient(app, raise_server_exceptions=False), operator


@pytest.fixture
def clients(tmp_path: Path) -> Iterator[list[tuple[TestClient, dict[str, str]]]]:
    out = []
    for fast in (True, False):
        client, operator = _client(tmp_path / str(fast), fast)
        client.__enter__()
        auth = {"Authorization": f"Bearer {operator}"}
        assert client.post("/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=auth).status_code == 201
        keys = {"operator": operator}
        for scope, device in (("device", "phone-1"), ("dashboard", None)):
            body: dict[str, Any] = {"scope": scope} | ({"device_id": device} if device else {})
            keys[scope] = client.post("/v1/buildings/hq/keys", json=body, headers=auth).json()["key"]
        out.append((client, keys))
    yield out
    for client, _ in out:
        client.__exit__(None, None, None)


def _exchange(client: TestClient, keys: dict[str, str], case: str) -> tuple[int, Any, str | None, str | None]:
    device = {"Authorization": f"Bearer {keys['device']}"}
    path, body, headers = "/v1/buildings/hq/batches", json.dumps(_batch(0)).encode(), device
    if case == "no key":
        headers = {}
    elif case == "unknown key":
        headers = {"Authorization": "Bearer csk_nope_nope"}
    elif case == "dashboard key":
        headers = {"Authorization": f"Bearer {keys['dashboard']}"}
    elif case == "other building":
        path = "/v1/buildings/elsewhere/batches"
    elif case == "too large":
        body = b"{" + b" " * 5_000 + b"}"
    elif case == "not json":
        body = b'{"building_id": "hq"'
    elif case == "invalid":
        body = json.dumps(_batch(0) | {"seq": -1}).encode()
    elif case == "retry":
        client.post(path, content=body, headers=device)
    r = client.post(path, content=body, headers={**headers, "Content-Type": "application/json"})
    payload = r.json()
    if isinstance(payload, dict) and "estimate" in payload and payload["estimate"]:
        payload["estimate"].pop("received_at_ms", None)
    return r.status_code, payload, r.headers.get("content-type"), r.headers.get("www-authenticate")


@pytest.mark.parametrize(
    "case",
    ["applied", "retry", "no key", "unknown key", "dashboard key", "other building", "too large", "not json",
     "invalid"],
)  # fmt: skip
def test_the_fast_path_answers_as_the_route_does(
    clients: list[tuple[TestClient, dict[str, str]]], case: str
) -> None:
    fast, routed = (_exchange(client, keys, case) for client, keys in clients)
    assert fast == routed
    status = fast[0]
    assert (status == 200) == (case in ("applied", "retry"))
    if status != 200:
        assert fast[2] == "application/problem+json"
        assert (fast[3] == "Bearer") == (status == 401)


def test_an_unexpected_error_answers_500_without_its_text_on_both_paths(
    clients: list[tuple[TestClient, dict[str, str]]], monkeypatch: pytest.MonkeyPatch
) -> None:
    async def broken(*args: object) -> bytes:
        raise RuntimeError("the secret of the ingest")

    monkeypatch.setattr(batches, "ingest", broken)
    fast, routed = (_exchange(client, keys, "applied") for client, keys in clients)
    assert fast == routed
    assert fast[0] == 500
    assert fast[2] == "application/problem+json"
    assert "secret" not in json.dumps(fast[1])
