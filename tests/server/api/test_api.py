"""The REST API end to end through the ASGI app: keys and scopes, the batch path, anchors, errors."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

from sqlalchemy import func, select

from server.store.db import make_engine, make_session_factory
from server.store.models import AnchorRow, BatchRow, PositionSnapshotRow
from tests.server.conftest import Api

T0 = 1_767_225_600_000


def _batch(seq: int, device: str = "phone-1", **extra: Any) -> dict[str, Any]:
    body: dict[str, Any] = {
        "building_id": "hq",
        "device_id": device,
        "batch_id": f"{device}-{seq}",
        "seq": seq,
        "steps": [
            {"t_ms": T0 + seq * 1000 + 100, "length_m": 0.7, "azimuth_rad": 1.5707963},
            {"t_ms": T0 + seq * 1000 + 700, "length_m": 0.7, "azimuth_rad": 1.5707963},
        ],
    }
    if seq == 0:
        body["landmarks"] = [
            {"kind": "fix", "t_ms": T0, "position": {"x_m": 5.0, "y_m": 5.0}, "sigma_m": 0.5}
        ]
    body.update(extra)
    return body


def _count(api: Api, model: type) -> int:
    engine = make_engine(api.url)
    try:
        with make_session_factory(engine)() as session:
            return int(session.execute(select(func.count()).select_from(model)).scalar_one())
    finally:
        engine.dispose()


def test_batches_track_a_user_and_retries_change_nothing(api: Api) -> None:
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    dashboard = api.key("hq", "dashboard")
    receipts = []
    for seq in range(5):
        r = api.client.post("/v1/buildings/hq/batches", json=_batch(seq), headers=api.auth(device))
        assert r.status_code == 200, r.text
        receipts.append(r.json())
    assert all(r["status"] == "applied" and r["tracking"] for r in receipts)
    last = receipts[-1]["estimate"]
    # 10 steps of 0.7 m east from (5, 5): about (12, 5)
    assert abs(last["position"]["x_m"] - 12.0) < 1.5
    assert abs(last["position"]["y_m"] - 5.0) < 1.5
    cov = last["covariance_m2"]
    assert cov[0][1] == cov[1][0]
    assert cov[0][0] > 0
    assert cov[0][0] * cov[1][1] > cov[0][1] ** 2
    snapshots = _count(api, PositionSnapshotRow)
    again = api.client.post("/v1/buildings/hq/batches", json=_batch(4), headers=api.auth(device))
    assert again.status_code == 200
    assert again.json()["status"] == "duplicate"
    assert again.json()["duplicate"]
    assert again.json()["estimate"] == last
    assert _count(api, PositionSnapshotRow) == snapshots
    assert _count(api, BatchRow) == 5
    late = _batch(3)
    late["batch_id"] = "phone-1-3-resent-as-new"
    r = api.client.post("/v1/buildings/hq/batches", json=late, headers=api.auth(device))
    assert r.json()["status"] == "late"
    assert r.json()["estimate"] == last
    positions = api.client.get("/v1/buildings/hq/positions", headers=api.auth(dashboard))
    assert positions.status_code == 200
    assert [p["user_id"] for p in positions.json()] == ["phone-1"]
    assert positions.json()[0]["position"] == last["position"]
    history = api.client.get("/v1/buildings/hq/users/phone-1/positions", headers=api.auth(dashboard))
    assert [h["t_ms"] for h in history.json()] == sorted(h["t_ms"] for h in history.json())
    assert len(history.json()) == 3  # one estimate a 2 s period of the phone's time (of 5, a second apart)


def test_steps_before_a_fix_are_skipped_with_a_warning(api: Api) -> None:
    api.create_building()
    device = api.key("hq", "device", "phone-2")
    body = _batch(1, "phone-2")
    r = api.client.post("/v1/buildings/hq/batches", json=body, headers=api.auth(device))
    assert r.status_code == 200
    assert r.json()["tracking"] is False
    assert r.json()["estimate"] is None
    assert "no position yet" in r.json()["warnings"][0]


def test_scopes_and_keys(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    api.create_building("other")
    device = api.key("hq", "device", "phone-1")
    dashboard = api.key("hq", "dashboard")
    cases = [
        ("post", "/v1/buildings/hq/batches", None, _batch(0), 401),
        ("post", "/v1/buildings/hq/batches", "csk_nope_nope", _batch(0), 401),
        ("post", "/v1/buildings/hq/batches", dashboard, _batch(0), 403),
        ("post", "/v1/buildings/hq/batches", device, _batch(0, "phone-9"), 403),
        ("get", "/v1/buildings/hq/positions", device, None, 403),
        ("get", "/v1/buildings/other/positions", dashboard, None, 403),
        ("post", "/v1/buildings/hq/keys", dashboard, {"scope": "dashboard"}, 403),
        ("post", "/v1/buildings", device, {"id": "x", "name": "X"}, 403),
        (
            "put",
            "/v1/buildings/hq/anchors/k1",
            dashboard,
            {"type": "elevator", "position": {"x_m": 1, "y_m": 1}},
            403,
        ),
    ]
    for method, path, key, body, expected in cases:
        headers = {} if key is None else api.auth(key)
        r = api.client.request(method, path, json=body, headers=headers)
        assert r.status_code == expected, (method, path, r.text)
        assert r.headers["content-type"].startswith("application/problem+json")
        assert r.json()["status"] == expected
        assert r.json()["detail"]
    r = api.client.post("/v1/buildings/hq/batches", json=_batch(0), headers={"Authorization": "Basic abc"})
    assert r.status_code == 401
    assert _count(api, BatchRow) == 0


def test_bad_batches_are_refused_and_change_nothing(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    good = _batch(0)
    nan_body = json.dumps(good).replace('"length_m": 0.7', '"length_m": NaN', 1)
    bad_rssi = copy.deepcopy(good)
    bad_rssi["wifi_scans"] = [
        {"t_ms": T0 + 500, "aps": [{"bssid": "00:11:22:33:44:55", "rssi_dbm": 12, "frequency_mhz": 2412}]}
    ]
    wrong_type = copy.deepcopy(good)
    wrong_type["seq"] = "first"
    other_building = copy.deepcopy(good)
    other_building["building_id"] = "elsewhere"
    cases: list[tuple[str, bytes, int, str]] = [
        ("nan", nan_body.encode(), 422, "steps.0.length_m"),
        ("rssi", json.dumps(bad_rssi).encode(), 422, "wifi_scans.0.aps.0.rssi_dbm"),
        ("type", json.dumps(wrong_type).encode(), 422, "seq"),
        ("not json", b"{steps:", 400, ""),
        ("empty", b"", 400, ""),
        ("oversize", b"{" + b" " * (2 * 1024 * 1024 + 10) + b"}", 413, ""),
        ("building mismatch", json.dumps(other_building).encode(), 422, ""),
    ]
    for name, body, status, loc in cases:
        r = api.client.post(
            "/v1/buildings/hq/batches",
            content=body,
            headers={**api.auth(device), "Content-Type": "application/json"},
        )
        assert r.status_code == status, (name, r.text)
        if loc:
            assert loc in [e["loc"] for e in r.json()["errors"]], name
    r = api.client.post("/v1/buildings/nowhere/batches", json=_batch(0), headers=api.auth(device))
    assert r.status_code == 403  # the key is not for that building: nothing is revealed about it
    assert _count(api, BatchRow) == 0
    assert _count(api, PositionSnapshotRow) == 0


def test_operator_pins_lists_merges_and_deletes_anchors(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building(geo=True)
    op = api.auth(api.operator)
    r = api.client.put(
        "/v1/buildings/hq/anchors/lift-a",
        json={"type": "elevator", "position": {"x_m": 10.0, "y_m": 20.0}, "label": "Lift A"},
        headers=op,
    )
    assert r.status_code == 200, r.text
    assert r.json()["known"]
    assert r.json()["label"] == "Lift A"
    r = api.client.put(
        "/v1/buildings/hq/anchors/stairs-b",
        json={"type": "stairs", "position": {"x_m": 30, "y_m": 5}},
        headers=op,
    )
    listed = api.client.get("/v1/buildings/hq/anchors", headers=op).json()
    assert {a["id"] for a in listed} == {"lift-a", "stairs-b"}
    assert api.client.get("/v1/buildings/hq/anchors/missing", headers=op).status_code == 404
    geo = api.client.get("/v1/buildings/hq/export.geojson", headers=op).json()
    lons = [f["geometry"]["coordinates"][0] for f in geo["features"]]
    assert all(-122.31 < lon < -122.29 for lon in lons)
    merged = api.client.post(
        "/v1/buildings/hq/anchors:merge", json={"anchor_ids": ["lift-a", "stairs-b"]}, headers=op
    )
    assert merged.status_code == 200
    assert merged.json()["id"] == "lift-a"
    assert api.client.delete("/v1/buildings/hq/anchors/lift-a", headers=op).status_code == 204
    assert api.client.get("/v1/buildings/hq/anchors", headers=op).json() == []
    assert _count(api, AnchorRow) == 0
    # a user starting at a known anchor's reading is placed there
    api.client.put(
        "/v1/buildings/hq/anchors/door-1", json={"type": "door", "position": {"x_m": 3, "y_m": 4}}, headers=op
    )
    device = api.key("hq", "device", "phone-1")
    body = {
        "building_id": "hq",
        "device_id": "phone-1",
        "batch_id": "b0",
        "seq": 0,
        "landmarks": [{"kind": "anchor", "t_ms": T0, "anchor_id": "door-1"}],
    }
    r = api.client.post("/v1/buildings/hq/batches", json=body, headers=api.auth(device))
    est = r.json()["estimate"]
    assert abs(est["position"]["x_m"] - 3) < 1.5
    assert abs(est["position"]["y_m"] - 4) < 1.5
    assert est["lat_deg"] is not None


def test_health_metrics_and_openapi(sqlite_api: Api) -> None:
    api = sqlite_api
    assert api.client.get("/healthz").json()["status"] == "ok"
    spec = api.client.get("/openapi.json").json()
    assert "SensorBatch" in spec["components"]["schemas"]
    assert "/v1/buildings/{building_id}/batches" in spec["paths"]
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    api.client.post("/v1/buildings/hq/batches", json=_batch(0), headers=api.auth(device))
    text = api.client.get("/metrics").text
    assert 'crowdslam_batches_total{building="hq"} 1.0' in text


def test_a_key_revoked_in_the_database_stops_working_when_its_cache_entry_expires(sqlite_api: Api) -> None:
    from datetime import UTC, datetime

    from sqlalchemy import update

    from server.auth import KeyCache
    from server.store.models import ApiKeyRow

    api = sqlite_api
    api.create_building()
    dashboard = api.key("hq", "dashboard")
    assert api.client.get("/v1/buildings/hq/positions", headers=api.auth(dashboard)).status_code == 200
    engine = make_engine(api.url)
    with make_session_factory(engine).begin() as session:
        session.execute(
            update(ApiKeyRow).where(ApiKeyRow.scope == "dashboard").values(revoked_at=datetime.now(UTC))
        )
    engine.dispose()
    # still remembered: the cache saves a query per request for its time to live
    assert api.client.get("/v1/buildings/hq/positions", headers=api.auth(dashboard)).status_code == 200
    state = api.client.app.state.crowdslam  # type: ignore[attr-defined]
    state.keys = KeyCache(ttl_s=0.0)
    r = api.client.get("/v1/buildings/hq/positions", headers=api.auth(dashboard))
    assert r.status_code == 401
    assert "revoked" in r.json()["detail"]


def test_key_cache_entries_expire_and_stay_bounded() -> None:
    from schemas.api import KeyScope
    from server.auth import KeyCache, Principal

    cache = KeyCache(ttl_s=10.0, max_entries=3)
    p = Principal(1, KeyScope.DEVICE, "hq", "phone-1")
    cache.put("a", p, now=0.0)
    assert cache.get("a", now=9.9) == p
    assert cache.get("a", now=10.1) is None
    assert cache.get("b", now=0.0) is None
    for i, key in enumerate("bcdef"):
        cache.put(key, p, now=20.0 + i)
    assert len(cache._entries) <= 3
    assert cache.get("f", now=25.0) == p


def test_revalidation_extends_valid_keys_and_forgets_revoked_ones() -> None:
    from schemas.api import KeyScope
    from server.auth import KeyCache, Principal

    cache = KeyCache(ttl_s=10.0)
    valid, revoked = Principal(1, KeyScope.DEVICE, "hq", "p1"), Principal(2, KeyScope.DEVICE, "hq", "p2")
    cache.put("a", valid, now=0.0)
    cache.put("b", revoked, now=0.0)
    assert cache.key_ids() == {1, 2}
    cache.revalidate({1}, checked_at=8.0)
    assert cache.get("a", now=17.9) == valid  # 10 s from the check, not from the first lookup
    assert cache.get("a", now=18.1) is None
    assert cache.get("b", now=1.0) is None
    assert cache.key_ids() == {1}


def test_a_revoked_key_stops_working_after_one_revalidation_round(sqlite_api: Api) -> None:
    import asyncio
    from datetime import UTC, datetime

    from sqlalchemy import update

    from server.api.deps import revalidate_keys
    from server.store.models import ApiKeyRow

    api = sqlite_api
    api.create_building()
    dashboard = api.key("hq", "dashboard")
    device = api.key("hq", "device", "phone-1")
    assert api.client.get("/v1/buildings/hq/positions", headers=api.auth(dashboard)).status_code == 200
    assert (
        api.client.post("/v1/buildings/hq/batches", json=_batch(0), headers=api.auth(device)).status_code
        == 200
    )
    engine = make_engine(api.url)
    with make_session_factory(engine).begin() as session:
        session.execute(
            update(ApiKeyRow).where(ApiKeyRow.scope == "dashboard").values(revoked_at=datetime.now(UTC))
        )
    engine.dispose()
    state = api.client.app.state.crowdslam  # type: ignore[attr-defined]
    assert api.client.get("/v1/buildings/hq/positions", headers=api.auth(dashboard)).status_code == 200
    cached = len(state.keys.key_ids())  # the operator's, the dashboard's and the device's
    asyncio.run(revalidate_keys(state))
    r = api.client.get("/v1/buildings/hq/positions", headers=api.auth(dashboard))
    assert r.status_code == 401
    assert "revoked" in r.json()["detail"]
    assert len(state.keys.key_ids()) == cached - 1  # only the dashboard's key was forgotten
    assert (
        api.client.post("/v1/buildings/hq/batches", json=_batch(1), headers=api.auth(device)).status_code
        == 200
    )


def test_raw_imu_and_a_strong_beacon_make_a_signature_anchor(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    device = api.key("hq", "device", "phone-raw")
    t = [T0 + 20 * i for i in range(200)]
    body = {
        "building_id": "hq",
        "device_id": "phone-raw",
        "batch_id": "raw-0",
        "seq": 0,
        "accelerometer": {"t_ms": t, "x": [0.0] * 200, "y": [0.0] * 200, "z": [9.81] * 200},
        "rotation_vector": {"t_ms": t, "x": [0.0] * 200, "y": [0.0] * 200, "z": [0.0] * 200},
        "landmarks": [{"kind": "fix", "t_ms": T0, "position": {"x_m": 5.0, "y_m": 5.0}, "sigma_m": 0.5}],
        "bluetooth": [
            {"kind": "beacon", "t_ms": T0 + 500 + 1000 * k, "mac": "C4:4F:33:12:34:56", "rssi_dbm": rssi}
            for k, rssi in enumerate([-60.0, -52.0, -58.0])
        ],
    }
    r = api.client.post("/v1/buildings/hq/batches", json=body, headers=api.auth(device))
    assert r.status_code == 200, r.text
    assert r.json()["tracking"]
    anchors = api.client.get("/v1/buildings/hq/anchors", headers=api.auth(api.operator)).json()
    assert [(a["type"], a["signature"]) for a in anchors] == [("beacon", "beacon:c4:4f:33:12:34:56")]
    assert abs(anchors[0]["position"]["x_m"] - 5.0) < 1.0
    engine = make_engine(api.url)
    try:
        with make_session_factory(engine)() as session:
            row = session.execute(select(AnchorRow)).scalar_one()
            assert row.signature == b"beacon:c4:4f:33:12:34:56"
    finally:
        engine.dispose()


def test_phones_stream_batches_over_a_websocket_with_the_same_answers(sqlite_api: Api) -> None:
    from datetime import UTC, datetime

    import pytest
    from sqlalchemy import update
    from starlette.websockets import WebSocketDisconnect

    from server.auth import KeyCache
    from server.store.models import ApiKeyRow

    api = sqlite_api
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    with (
        pytest.raises(WebSocketDisconnect) as refused,
        api.client.websocket_connect("/v1/buildings/hq/stream?token=nope") as ws,
    ):
        ws.receive_text()
    assert refused.value.code == 4401
    with api.client.websocket_connect(f"/v1/buildings/hq/stream?token={device}") as ws:
        ws.send_text(json.dumps(_batch(0)))
        first = json.loads(ws.receive_text())
        assert first["status"] == "applied"
        assert first["tracking"] is True
        ws.send_text(json.dumps(_batch(0)))  # a retry answers duplicate and changes nothing
        assert json.loads(ws.receive_text())["duplicate"] is True
        ws.send_text('{"building_id": "hq", "device_id": "phone-1"')  # truncated JSON
        problem = json.loads(ws.receive_text())
        assert problem["status"] == 400  # not JSON: a Problem, and the stream goes on
        ws.send_text(json.dumps(_batch(1, device="phone-2")))  # posting as another device
        assert json.loads(ws.receive_text())["status"] == 403
        ws.send_text(json.dumps(_batch(1)))
        assert json.loads(ws.receive_text())["status"] == "applied"
        # the key is revoked in the database: once the cache forgets it, the stream is closed
        engine = make_engine(api.url)
        with make_session_factory(engine).begin() as session:
            session.execute(
                update(ApiKeyRow).where(ApiKeyRow.scope == "device").values(revoked_at=datetime.now(UTC))
            )
        engine.dispose()
        api.client.app.state.crowdslam.keys = KeyCache(ttl_s=0.0)  # type: ignore[attr-defined]
        ws.send_text(json.dumps(_batch(2)))
        assert json.loads(ws.receive_text())["status"] == 401
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_text()
        assert closed.value.code == 4401
    assert _count(api, BatchRow) == 2


def test_fastapi_telemetry_is_off_unless_asked_for(tmp_path: Path) -> None:
    """Off by default (each request would otherwise look its OpenTelemetry providers up in the environment);
    the setting hands FastAPI its own defaults back."""
    from server.app import create_app
    from server.settings import Settings

    quiet = create_app(Settings(data_dir=tmp_path))
    assert not quiet._native_telemetry.enabled()
    assert not any(quiet._telemetry[k] for k in ("tracing", "metrics", "logs"))
    traced = create_app(Settings(data_dir=tmp_path, fastapi_telemetry=True))
    assert all(traced._telemetry[k] for k in ("tracing", "metrics", "logs"))
