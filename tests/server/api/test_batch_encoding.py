"""A batch body may be gzip-compressed (``Content-Encoding: gzip``): applied as the same JSON would be; one
that inflates beyond the batch limit, is not gzip, or names another encoding is refused and changes
nothing."""

from __future__ import annotations

import gzip
import json

from server.store.models import BatchRow
from tests.server.api.test_api import _batch, _count
from tests.server.conftest import Api

BATCHES = "/v1/buildings/hq/batches"


def test_a_gzip_batch_is_applied_as_its_json(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    device = api.auth(api.key("hq", "device", "phone-1"))
    plain = api.client.post(BATCHES, json=_batch(0), headers=device)
    body = gzip.compress(json.dumps(_batch(1)).encode())
    zipped = api.client.post(BATCHES, content=body, headers=device | {"Content-Encoding": "gzip"})
    assert zipped.status_code == 200, zipped.text
    assert zipped.json()["status"] == "applied"
    assert zipped.json()["estimate"]["t_ms"] > plain.json()["estimate"]["t_ms"]
    again = api.client.post(BATCHES, content=body, headers=device | {"Content-Encoding": "GZIP"})
    assert again.json()["status"] == "duplicate"  # the same batch id, recognised through the encoding
    assert _count(api, BatchRow) == 2


def test_bad_encodings_are_refused_and_change_nothing(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    device = api.auth(api.key("hq", "device", "phone-1"))
    limit = api.settings.max_batch_bytes
    bomb = gzip.compress(b" " * (limit + 1) + json.dumps(_batch(0)).encode())  # whitespace: valid JSON
    assert len(bomb) < limit // 100
    cases = [
        (bomb, "gzip", 413, "decompressed"),
        (b"not gzip at all", "gzip", 400, "not gzip"),
        (gzip.compress(json.dumps(_batch(0)).encode())[:-6], "gzip", 400, "cut short"),
        (gzip.compress(json.dumps(_batch(0)).encode()) + b"tail", "gzip", 400, "after its end"),
        (json.dumps(_batch(0)).encode(), "br", 415, "'br' is not accepted"),
    ]
    for body, encoding, status, says in cases:
        r = api.client.post(BATCHES, content=body, headers=device | {"Content-Encoding": encoding})
        assert r.status_code == status, (encoding, says, r.text)
        assert r.headers["content-type"] == "application/problem+json"
        assert says in r.json()["detail"]
    assert _count(api, BatchRow) == 0
    identity = api.client.post(BATCHES, json=_batch(0), headers=device | {"Content-Encoding": "identity"})
    assert identity.json()["status"] == "applied"
