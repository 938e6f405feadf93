"""Limits meet a request before any work: a body over the limit is refused with 413 on its declared length
and while it streams, before the key is looked up; JSON nested past the parser's depth is a 400, not a 500."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from server.app import create_app
from server.rate_limit import RateLimiter
from server.settings import Settings
from tests.server.api.test_api import _batch
from tests.server.conftest import Api, migrate_with_operator


def test_an_anonymous_huge_body_is_refused_before_the_key_is_checked(sqlite_api: Api) -> None:
    api = sqlite_api
    limit = api.settings.max_request_bytes
    # declared: refused on the header alone, whatever follows
    response = api.client.post(
        "/v1/buildings", content=b"{}", headers={"content-length": str(400 * 1024 * 1024)}
    )
    assert response.status_code == 413
    assert response.headers["content-type"] == "application/problem+json"
    assert str(limit) in response.json()["detail"]

    # streamed without a length: refused once the limit is passed (the app reads no further)
    def chunks() -> Iterator[bytes]:
        for _ in range(1000):
            yield b" " * 65536

    response = api.client.post("/v1/buildings", content=chunks())
    assert response.status_code == 413
    # a body just under the limit goes on to authentication
    response = api.client.post("/v1/buildings", content=b" " * (limit - 10))
    assert response.status_code == 401


def test_a_malformed_content_length_is_a_400(sqlite_api: Api) -> None:
    response = sqlite_api.client.post("/v1/buildings", content=b"{}", headers={"content-length": "lots"})
    assert response.status_code == 400


def test_json_nested_5000_deep_is_a_400_on_every_route(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    deep = b'{"building_id": ' + b"[" * 5000 + b"]" * 5000 + b"}"
    response = api.client.post("/v1/buildings/hq/batches", content=deep, headers=api.auth(device))
    assert response.status_code == 400, response.text
    assert "recursion" in response.json()["detail"]
    response = api.client.post(
        "/v1/buildings", content=deep, headers={**api.auth(api.operator), "content-type": "application/json"}
    )
    assert response.status_code in (400, 422), response.text


def _api_with(tmp_path: Path, **settings: object) -> Iterator[Api]:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    config = Settings(data_dir=tmp_path / "data", database_url=url, **settings)  # type: ignore[arg-type]
    with TestClient(create_app(config)) as client:
        yield Api(client, operator, url, config)


def test_a_device_key_posting_too_fast_gets_429_with_retry_after(tmp_path: Path) -> None:
    for api in _api_with(tmp_path, device_rate_per_s=1.0, device_burst=3.0):
        api.create_building()
        key = api.key("hq", "device", "phone-1")
        statuses = [
            api.client.post("/v1/buildings/hq/batches", json=_batch(seq), headers=api.auth(key)).status_code
            for seq in range(5)
        ]
        assert statuses[:3] == [200, 200, 200]
        assert 429 in statuses[3:]
        refused = api.client.post("/v1/buildings/hq/batches", json=_batch(5), headers=api.auth(key))
        assert refused.status_code == 429
        assert int(refused.headers["retry-after"]) >= 1
        # another phone of the building is not held back by this one
        other = api.key("hq", "device", "phone-2")
        ok = api.client.post("/v1/buildings/hq/batches", json=_batch(0, "phone-2"), headers=api.auth(other))
        assert ok.status_code == 200


def test_the_default_rate_never_meets_a_phone_posting_once_a_second() -> None:
    limiter = RateLimiter(Settings().device_rate_per_s, Settings().device_burst)
    assert all(limiter.take(1, now=float(t)) == 0.0 for t in range(3600))
    burst = RateLimiter(1.0, 3.0)
    assert [burst.take(1, now=0.0) for _ in range(4)][-1] == pytest.approx(1.0)


def test_live_sockets_per_key_are_capped(tmp_path: Path) -> None:
    for api in _api_with(tmp_path, max_live_sockets_per_key=2):
        api.create_building()
        dashboard = api.key("hq", "dashboard")
        url = f"/v1/buildings/hq/live?token={dashboard}"
        with api.client.websocket_connect(url), api.client.websocket_connect(url):
            with api.client.websocket_connect(url) as third, pytest.raises(WebSocketDisconnect) as closed:
                third.receive_text()
            assert closed.value.code == 4429
        # both closed: room again
        with api.client.websocket_connect(url) as again:
            again.close()


def test_metrics_can_require_a_site_wide_operator_key(tmp_path: Path) -> None:
    for api in _api_with(tmp_path, metrics_need_key=True):
        api.create_building()
        assert api.client.get("/metrics").status_code == 401
        building_operator = api.key("hq", "operator")
        assert api.client.get("/metrics", headers=api.auth(building_operator)).status_code == 403
        response = api.client.get("/metrics", headers=api.auth(api.operator))
        assert response.status_code == 200
        assert "crowdslam_batches" in response.text
