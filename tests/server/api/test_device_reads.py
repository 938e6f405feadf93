"""What a device key may read: its building, the floors' plans (a phone draws itself on them) and its own
device's latest estimate; never another device's, another user's history, or the crowd's positions."""

from __future__ import annotations

from schemas.floor_plans import FLOOR_PLAN_EXAMPLE
from tests.server.api.test_api import _batch
from tests.server.conftest import Api


def test_a_device_key_reads_its_own_position_and_nobody_elses(api: Api) -> None:
    api.create_building(size_m=(60.0, 50.0))
    api.create_building("annex", size_m=(60.0, 50.0))
    mine, theirs = api.key("hq", "device", "phone-1"), api.key("hq", "device", "phone-2")
    elsewhere = api.key("annex", "device", "phone-1")
    dashboard = api.key("hq", "dashboard")
    own = "/v1/buildings/hq/devices/phone-1/position"

    # before its first batch, and before its first fix: not placed, said as such
    before = api.client.get(own, headers=api.auth(mine))
    assert before.status_code == 200, before.text
    assert before.json() == {"device_id": "phone-1", "user_id": None, "estimate": None}
    unplaced = _batch(0, "phone-1")
    del unplaced["landmarks"]
    assert (
        api.client.post("/v1/buildings/hq/batches", json=unplaced, headers=api.auth(mine)).status_code == 200
    )
    waiting = api.client.get(own, headers=api.auth(mine)).json()
    assert waiting == {"device_id": "phone-1", "user_id": "phone-1", "estimate": None}

    for seq, fix in ((1, True), (2, False)):
        body = _batch(seq, "phone-1")
        if fix:
            body["landmarks"] = [
                {"kind": "fix", "t_ms": body["steps"][0]["t_ms"] - 50, "position": {"x_m": 5.0, "y_m": 5.0}}
            ]
        r = api.client.post("/v1/buildings/hq/batches", json=body, headers=api.auth(mine))
        assert r.status_code == 200, r.text
    receipt = r.json()
    assert (
        api.client.post(
            "/v1/buildings/hq/batches", json=_batch(0, "phone-2"), headers=api.auth(theirs)
        ).status_code
        == 200
    )

    read = api.client.get(own, headers=api.auth(mine))
    assert read.status_code == 200, read.text
    # what the last receipt said (the stored estimate keeps no best particle)
    assert read.json()["estimate"] == {**receipt["estimate"], "best_particle": None}
    # a dashboard reads any device's; an operator too
    assert api.client.get(own, headers=api.auth(dashboard)).json() == read.json()
    assert api.client.get(own, headers=api.auth(api.operator)).status_code == 200

    # never another device's, another building's, the crowd's, or a user's history
    other = api.client.get("/v1/buildings/hq/devices/phone-2/position", headers=api.auth(mine))
    assert other.status_code == 403
    assert "its own device only" in other.json()["detail"]
    assert api.client.get(own, headers=api.auth(elsewhere)).status_code == 403
    assert api.client.get("/v1/buildings/hq/positions", headers=api.auth(mine)).status_code == 403
    for user in ("phone-1", "phone-2"):
        history = api.client.get(f"/v1/buildings/hq/users/{user}/positions", headers=api.auth(mine))
        assert history.status_code == 403
    assert api.client.get("/v1/buildings/hq/zones", headers=api.auth(mine)).status_code == 403
    assert (
        api.client.get(
            "/v1/buildings/nowhere/devices/phone-1/position", headers=api.auth(api.operator)
        ).status_code
        == 404
    )


def test_a_device_key_reads_its_building_and_floor_plans_only(api: Api) -> None:
    api.create_building(size_m=(60.0, 50.0))
    api.create_building("annex", size_m=(60.0, 50.0))
    put = api.client.put(
        "/v1/buildings/hq/floors/0/plan", json=FLOOR_PLAN_EXAMPLE, headers=api.auth(api.operator)
    )
    assert put.status_code == 200, put.text
    device = api.auth(api.key("hq", "device", "phone-1"))
    building = api.client.get("/v1/buildings/hq", headers=device)
    assert building.status_code == 200
    assert building.json()["floors"][0]["width_m"] == 60.0
    assert api.client.get("/v1/buildings/hq/floor-plans", headers=device).json() == [0]
    plan = api.client.get("/v1/buildings/hq/floors/0/plan", headers=device)
    assert plan.status_code == 200
    assert plan.json()["features"]
    assert [b["id"] for b in api.client.get("/v1/buildings", headers=device).json()] == ["hq"]
    for path in (
        "/v1/buildings/annex",
        "/v1/buildings/annex/floor-plans",
        "/v1/buildings/annex/floors/0/plan",
    ):
        assert api.client.get(path, headers=device).status_code == 403, path
    # writing stays an operator's
    assert (
        api.client.put("/v1/buildings/hq/floors/0/plan", json=FLOOR_PLAN_EXAMPLE, headers=device).status_code
        == 403
    )
