"""Zones through the API: drawn, validated with clear errors, listed with their occupancy, and the visits a
walking user makes, stored with its batches, told live, kept over a restart, and counted at a past time. On
SQLite and PostgreSQL."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from schemas.zones import ZONE_EXAMPLE
from server.app import create_app
from tests.server.api.test_api import T0, _batch
from tests.server.conftest import Api

ZONES = "/v1/buildings/hq/zones"


def _zone(x0: float, x1: float, y0: float = 0.0, y1: float = 10.0, **extra: Any) -> dict[str, Any]:
    ring = [[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]
    return {"floor": 0, "name": "Shop front", "polygon": {"type": "Polygon", "coordinates": [ring]}} | extra


def _walk(seq: int, device: str = "phone-1") -> dict[str, Any]:
    """A second of walking east at 1.4 m/s along y = 5 (``test_api``'s batch), from a fix at x = 5 m at T0
    sure to 0.3 m: the cloud starts narrower than a zone's edge."""
    body = _batch(seq, device)
    if seq == 0:
        body["landmarks"][0]["sigma_m"] = 0.3
    return body


def test_zones_are_drawn_listed_and_deleted(api: Api) -> None:
    api.create_building(size_m=(60.0, 50.0))
    op, dashboard = api.auth(api.operator), api.auth(api.key("hq", "dashboard"))
    put = api.client.put(f"{ZONES}/cafe", json=ZONE_EXAMPLE, headers=op)
    assert put.status_code == 200, put.text
    assert put.json() == ZONE_EXAMPLE | {"id": "cafe", "occupancy": 0}
    assert api.client.put(f"{ZONES}/cafe", json=ZONE_EXAMPLE, headers=op).json() == put.json()  # a retry
    assert api.client.put(f"{ZONES}/gate", json=_zone(30, 35), headers=op).status_code == 200
    listed = api.client.get(ZONES, headers=dashboard)
    assert [z["id"] for z in listed.json()] == ["cafe", "gate"]
    assert api.client.get(f"{ZONES}/gate", headers=dashboard).json()["polygon"] == _zone(30, 35)["polygon"]
    occupancy = api.client.get(f"{ZONES}/occupancy", headers=dashboard)
    assert occupancy.status_code == 200
    assert occupancy.json()["zones"] == {"cafe": 0, "gate": 0}
    reserved = api.client.put(f"{ZONES}/occupancy", json=ZONE_EXAMPLE, headers=op)
    assert reserved.status_code == 422
    assert "may not be named 'occupancy'" in reserved.json()["detail"]
    options = api.client.options(f"{ZONES}/occupancy", headers=op)
    assert options.status_code == 405
    assert options.headers["allow"] == "GET, HEAD"
    assert api.client.delete(f"{ZONES}/gate", headers=dashboard).status_code == 403
    assert api.client.put(f"{ZONES}/x", json=_zone(1, 2), headers=dashboard).status_code == 403
    assert api.client.delete(f"{ZONES}/gate", headers=op).status_code == 204
    assert api.client.delete(f"{ZONES}/gate", headers=op).status_code == 404
    assert api.client.get(f"{ZONES}/gate", headers=dashboard).status_code == 404
    assert api.client.get(f"{ZONES}/gate/visits", headers=dashboard).status_code == 404
    assert [z["id"] for z in api.client.get(ZONES, headers=dashboard).json()] == ["cafe"]
    device = api.auth(api.key("hq", "device", "phone-1"))
    assert api.client.get(ZONES, headers=device).status_code == 403
    assert api.client.get("/v1/buildings/nowhere/zones", headers=op).status_code == 404


def _bowtie() -> dict[str, Any]:
    return _zone(0, 1) | {
        "polygon": {"type": "Polygon", "coordinates": [[[0, 0], [4, 4], [4, 0], [0, 4], [0, 0]]]}
    }


@pytest.mark.parametrize(
    ("body", "status", "says"),
    [
        (_bowtie(), 422, "crosses itself: its edges 0 and 2"),
        (_zone(0, 1) | {"floor": 3}, 404, "has no floor 3"),
        (_zone(50, 400), 422, "outside the building"),
        (_zone(1, 1), 422, "no area"),
        (
            _zone(0, 1)
            | {"polygon": {"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, 1], [0, 0]]] * 2}},
            422,
            "one ring",
        ),
        (
            _zone(0, 1) | {"polygon": {"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, 1], [0, 1]]]}},
            422,
            "first",
        ),
        (_zone(0, 1) | {"dwell_s": -5}, 422, "dwell_s"),
        (_zone(0, 1) | {"polygon": {"type": "Point", "coordinates": [1, 1]}}, 422, "Polygon"),
    ],
)
def test_bad_zones_are_refused_and_change_nothing(sqlite_api: Api, body: Any, status: int, says: str) -> None:
    api = sqlite_api
    api.create_building(size_m=(60.0, 50.0))
    op = api.auth(api.operator)
    r = api.client.put(f"{ZONES}/z", json=body, headers=op)
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/problem+json"
    assert says in r.text
    assert api.client.get(ZONES, headers=op).json() == []


def test_a_walk_through_a_zone_is_one_visit_told_live_and_kept_over_a_restart(api: Api) -> None:
    api.create_building(size_m=(60.0, 50.0))
    op, dashboard_key = api.auth(api.operator), api.key("hq", "dashboard")
    dashboard = api.auth(dashboard_key)
    device = api.auth(api.key("hq", "device", "phone-1"))
    zone_messages = []
    # the fixture's app never loads the building: two apps in turn serve it, the second after a restart
    with TestClient(create_app(api.settings)) as first:
        assert first.put(f"{ZONES}/front", json=_zone(9, 15, dwell_s=1.0), headers=op).status_code == 200
        with first.websocket_connect(f"/v1/buildings/hq/live?token={dashboard_key}") as live:
            for seq in range(6):  # to x ~ 13.4: inside
                r = first.post("/v1/buildings/hq/batches", json=_walk(seq), headers=device)
                assert r.status_code == 200, r.text
                while (m := live.receive_json())["type"] != "position":
                    if m["type"] == "zone":
                        zone_messages.append(m)
        assert [m["kind"] for m in zone_messages] == ["enter", "dwell"]
        assert zone_messages[0]["user_id"] == "phone-1"
        assert zone_messages[0]["probability"] >= 0.8
        assert first.get(f"{ZONES}/front", headers=dashboard).json()["occupancy"] == 1
        visits = first.get(f"{ZONES}/front/visits", headers=dashboard).json()
        assert len(visits) == 1
        assert visits[0]["left_ms"] is None
        assert visits[0]["dwelled"]
        entered = visits[0]["entered_ms"]
        assert T0 + 2_000 <= entered <= T0 + 5_000

    # the user is still inside after the restart: leaving closes the same visit, not a new one
    with TestClient(create_app(api.settings)) as again:
        for seq in range(6, 14):  # to x ~ 24: out
            r = again.post("/v1/buildings/hq/batches", json=_walk(seq), headers=device)
            assert r.status_code == 200, r.text
        visits = again.get(f"{ZONES}/front/visits", headers=dashboard).json()
        assert len(visits) == 1, visits
        left = visits[0]["left_ms"]
        assert left is not None
        assert T0 + 7_000 <= left <= T0 + 12_000
        assert visits[0]["seconds"] == (left - entered) / 1000
        assert again.get(f"{ZONES}/front", headers=dashboard).json()["occupancy"] == 0
        during = again.get(f"{ZONES}/occupancy", params={"at": (entered + left) // 2}, headers=dashboard)
        assert during.json() == {"at_ms": (entered + left) // 2, "zones": {"front": 1}}
        after = again.get(f"{ZONES}/occupancy", params={"at": left + 1}, headers=dashboard)
        assert after.json()["zones"] == {"front": 0}
        since = again.get(f"{ZONES}/front/visits", params={"since": left + 1}, headers=dashboard)
        assert since.json() == []
        # a person forgotten on request takes its visits along
        assert again.delete("/v1/buildings/hq/users/phone-1", headers=op).status_code == 204
        assert again.get(f"{ZONES}/front/visits", headers=dashboard).json() == []
