"""What a dashboard reads besides positions: the key it holds, the floors with a plan, the building as it was
at a past time, and finished signal maps. On SQLite and PostgreSQL."""

from __future__ import annotations

from schemas.floor_plans import FLOOR_PLAN_EXAMPLE
from tests.server.api.test_api import T0, _batch
from tests.server.conftest import Api


def test_the_key_presented_says_what_it_may_do(api: Api) -> None:
    api.create_building()
    dashboard, device = api.key("hq", "dashboard"), api.key("hq", "device", "phone-1")
    assert api.client.get("/v1/key", headers=api.auth(api.operator)).json() == {
        "scope": "operator",
        "building_id": None,
        "device_id": None,
    }
    assert api.client.get("/v1/key", headers=api.auth(dashboard)).json()["building_id"] == "hq"
    assert api.client.get("/v1/key", headers=api.auth(device)).json() == {
        "scope": "device",
        "building_id": "hq",
        "device_id": "phone-1",
    }
    for headers in ({}, api.auth("csk_00000000_nope")):
        refused = api.client.get("/v1/key", headers=headers)
        assert refused.status_code == 401
        assert refused.headers["content-type"] == "application/problem+json"


def test_floor_plans_are_listed_by_level(api: Api) -> None:
    api.create_building(size_m=(60.0, 50.0))
    dashboard = api.auth(api.key("hq", "dashboard"))
    assert api.client.get("/v1/buildings/hq/floor-plans", headers=dashboard).json() == []
    put = api.client.put(
        "/v1/buildings/hq/floors/0/plan", json=FLOOR_PLAN_EXAMPLE, headers=api.auth(api.operator)
    )
    assert put.status_code == 200, put.text
    assert api.client.get("/v1/buildings/hq/floor-plans", headers=dashboard).json() == [0]
    # a phone draws itself on its building's plans: its device key lists them too
    device = api.auth(api.key("hq", "device", "phone-1"))
    assert api.client.get("/v1/buildings/hq/floor-plans", headers=device).json() == [0]
    assert (
        api.client.get("/v1/buildings/nowhere/floor-plans", headers=dashboard).status_code == 403
    )  # not its own
    nowhere = api.client.get("/v1/buildings/nowhere/floor-plans", headers=api.auth(api.operator))
    assert nowhere.status_code == 404


def test_positions_at_a_past_time_are_each_users_newest_then(api: Api) -> None:
    api.create_building()
    dashboard = api.auth(api.key("hq", "dashboard"))
    for device in ("phone-1", "phone-2"):
        key = api.auth(api.key("hq", "device", device))
        for seq in range(10 if device == "phone-1" else 2):  # a history row every 2 s: five of phone-1
            r = api.client.post("/v1/buildings/hq/batches", json=_batch(seq, device), headers=key)
            assert r.status_code == 200, r.text
    history = api.client.get(
        "/v1/buildings/hq/users/phone-1/positions", headers=dashboard, params={"limit": 100}
    ).json()
    at = history[3]["t_ms"]
    then = api.client.get("/v1/buildings/hq/positions", headers=dashboard, params={"at_ms": at}).json()
    by_user = {e["user_id"]: e for e in then}
    assert set(by_user) == {"phone-1", "phone-2"}
    assert by_user["phone-1"] == history[3]  # its newest estimate at that time, not its latest
    assert by_user["phone-2"]["t_ms"] <= at
    # a narrow window leaves out a user not heard from within it
    narrow = api.client.get(
        "/v1/buildings/hq/positions",
        headers=dashboard,
        params={"at_ms": history[-1]["t_ms"], "window_ms": 1500},
    ).json()
    assert [e["user_id"] for e in narrow] == ["phone-1"]
    assert (
        api.client.get("/v1/buildings/hq/positions", headers=dashboard, params={"at_ms": T0 - 10**6}).json()
        == []
    )
    for bad in ({"at_ms": -5}, {"at_ms": T0, "window_ms": 0}, {"at_ms": T0, "window_ms": 10**8}):
        refused = api.client.get("/v1/buildings/hq/positions", headers=dashboard, params=bad)
        assert refused.status_code == 422, bad
    # without at_ms, every user's latest as before: its last batch's, which the history may have skipped
    latest = api.client.get("/v1/buildings/hq/positions", headers=dashboard).json()
    assert {e["user_id"]: e["t_ms"] for e in latest}["phone-1"] == T0 + 9 * 1000 + 700 >= history[-1]["t_ms"]


def test_dashboards_read_signal_map_builds_and_only_operators_start_them(api: Api) -> None:
    api.create_building()
    dashboard = api.auth(api.key("hq", "dashboard"))
    assert api.client.get("/v1/buildings/hq/signal-maps", headers=dashboard).json() == []
    assert api.client.get("/v1/buildings/hq/signal-maps/abc", headers=dashboard).status_code == 404
    refused = api.client.post("/v1/buildings/hq/signal-maps", headers=dashboard)
    assert refused.status_code == 403
    device = api.auth(api.key("hq", "device", "phone-1"))
    assert api.client.get("/v1/buildings/hq/signal-maps", headers=device).status_code == 403
