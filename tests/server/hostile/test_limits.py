"""Limits meet a request before any work: a body over the limit is refused with 413 on its declared length
and while it streams, before the key is looked up; JSON nested past the parser's depth is a 400, not a 500."""

from __future__ import annotations

from collections.abc import Iterator

from tests.server.conftest import Api


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
