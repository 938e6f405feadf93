"""A building of several floors through the API: a fix names its floor, estimates and stored positions say it
(and how sure the filter is), a change of floor moves the user, and a floor the building does not have is
refused with 422."""

from __future__ import annotations

from typing import Any

from tests.server.api.test_api import T0, _batch
from tests.server.conftest import Api

FLOORS = [
    {"level": 0, "name": "Ground", "width_m": 60.0, "height_m": 40.0, "elevation_m": 0.0},
    {"level": 1, "name": "First", "width_m": 60.0, "height_m": 40.0, "elevation_m": 5.0},
    {"level": 2, "name": "Second", "width_m": 60.0, "height_m": 40.0, "elevation_m": 9.0},
]


def _tower(api: Api) -> None:
    body = {"id": "hq", "name": "HQ", "floors": FLOORS}
    created = api.client.post("/v1/buildings", json=body, headers=api.auth(api.operator))
    assert created.status_code == 201, created.text


def _fix_on(level: int) -> list[dict[str, Any]]:
    return [{"kind": "fix", "t_ms": T0, "position": {"x_m": 5.0, "y_m": 5.0}, "sigma_m": 0.5, "floor": level}]


def test_a_fix_names_the_floor_and_the_estimates_say_it(api: Api) -> None:
    _tower(api)
    device = api.auth(api.key("hq", "device", "phone-1"))
    first = api.client.post("/v1/buildings/hq/batches", json=_batch(0, landmarks=_fix_on(1)), headers=device)
    assert first.status_code == 200, first.text
    estimate = first.json()["estimate"]
    assert estimate["floor"] == 1
    assert estimate["floor_probability"] > 0.99
    # stairs up with the barometer's rise of one storey (5 m to the second floor's 9 m: 4 m), a few seconds
    # on (the history keeps a point every 2 s)
    climb = _batch(3, anchor_detections=[{"t_ms": T0 + 3_500, "type": "stairs", "rise_m": 4.1}])
    moved = api.client.post("/v1/buildings/hq/batches", json=climb, headers=device)
    assert moved.status_code == 200, moved.text
    assert moved.json()["estimate"]["floor"] == 2
    reader = api.auth(api.key("hq", "dashboard"))
    (latest,) = api.client.get("/v1/buildings/hq/positions", headers=reader).json()
    assert latest["floor"] == 2
    assert latest["floor_probability"] > 0.9
    history = api.client.get("/v1/buildings/hq/users/phone-1/positions", headers=reader).json()
    assert [p["floor"] for p in history] == [1, 2]


def test_a_floor_the_building_does_not_have_is_refused(api: Api) -> None:
    _tower(api)
    device = api.auth(api.key("hq", "device", "phone-1"))
    refused = api.client.post(
        "/v1/buildings/hq/batches", json=_batch(0, landmarks=_fix_on(5)), headers=device
    )
    assert refused.status_code == 422
    assert refused.headers["content-type"] == "application/problem+json"
    assert "has no floor 5; its floors: 0, 1, 2" in refused.json()["detail"]
    operator = api.auth(api.operator)
    pinned = api.client.put(
        "/v1/buildings/hq/anchors/lift-up",
        json={"floor": 4, "type": "elevator", "position": {"x_m": 10.0, "y_m": 10.0}},
        headers=operator,
    )
    assert pinned.status_code == 422
    assert "has no floor 4" in pinned.json()["detail"]


def test_a_known_anchor_keeps_its_floor_and_places_a_reading_there(api: Api) -> None:
    _tower(api)
    operator = api.auth(api.operator)
    pinned = api.client.put(
        "/v1/buildings/hq/anchors/lift-2",
        json={"floor": 2, "type": "elevator", "position": {"x_m": 10.0, "y_m": 10.0}, "label": "lift"},
        headers=operator,
    )
    assert pinned.status_code in (200, 201), pinned.text
    assert pinned.json()["floor"] == 2
    device = api.auth(api.key("hq", "device", "phone-1"))
    reading = [{"kind": "anchor", "t_ms": T0, "anchor_id": "lift-2"}]
    first = api.client.post("/v1/buildings/hq/batches", json=_batch(0, landmarks=reading), headers=device)
    assert first.status_code == 200, first.text
    assert first.json()["estimate"]["floor"] == 2
    anchors = api.client.get("/v1/buildings/hq/anchors", headers=operator).json()
    assert [(a["id"], a["floor"]) for a in anchors if a["known"]] == [("lift-2", 2)]


def test_a_building_without_floors_is_floor_zero(api: Api) -> None:
    api.create_building()
    device = api.auth(api.key("hq", "device", "phone-1"))
    estimate = api.client.post("/v1/buildings/hq/batches", json=_batch(0), headers=device).json()["estimate"]
    assert (estimate["floor"], estimate["floor_probability"]) == (0, 1.0)
    refused = api.client.post(
        "/v1/buildings/hq/batches", json=_batch(1, landmarks=_fix_on(1)), headers=device
    )
    assert refused.status_code == 422
