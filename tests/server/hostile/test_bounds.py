"""Every number a client sends is finite and physically possible, and every time is near the server's
clock: out-of-bounds input is refused (422, naming the field) before anything is touched, and the user it
came from goes on being tracked."""

from __future__ import annotations

import time
from typing import Any

import httpx

from tests.server.api.test_api import _batch
from tests.server.conftest import Api


def _post(api: Api, key: str, body: dict[str, Any]) -> httpx.Response:
    return api.client.post("/v1/buildings/hq/batches", json=body, headers=api.auth(key))


def test_an_absurd_fix_is_refused_and_its_user_goes_on(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    key = api.key("hq", "device", "phone-1")
    assert _post(api, key, _batch(0)).json()["status"] == "applied"
    absurd = _batch(
        1,
        landmarks=[
            {"kind": "fix", "t_ms": _batch(1)["steps"][0]["t_ms"], "position": {"x_m": 1e160, "y_m": 0}}
        ],
    )
    response = _post(api, key, absurd)
    assert response.status_code == 422, response.text
    assert "landmarks.0.fix.position.x_m" in response.text
    # nothing was kept: the same batch id, sane, applies
    sane = _post(api, key, _batch(1))
    assert sane.status_code == 200
    assert sane.json()["status"] == "applied"
    assert sane.json()["estimate"] is not None
    assert _post(api, key, _batch(2)).json()["status"] == "applied"


def test_an_anchor_cannot_be_pinned_far_away_and_imu_is_bounded(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    response = api.client.put(
        "/v1/buildings/hq/anchors/far",
        json={"type": "door", "position": {"x_m": 1e308, "y_m": 0.0}},
        headers=api.auth(api.operator),
    )
    assert response.status_code == 422, response.text
    key = api.key("hq", "device", "phone-1")
    t0 = _batch(0)["steps"][0]["t_ms"]
    imu = _batch(
        0,
        steps=[],
        accelerometer={"t_ms": [t0, t0 + 20], "x": [0.0, 1e300], "y": [0.0, 0.0], "z": [9.8, 9.8]},
    )
    response = _post(api, key, imu)
    assert response.status_code == 422, response.text
    assert "accelerometer.x.1" in response.text


def test_positions_outside_the_buildings_extent_are_refused(api: Api) -> None:
    """A building's floors give its extent; a fix, GPS fix or anchor beyond it plus the operator's margin
    (1 km by default) is 422 and changes nothing. On SQLite and PostgreSQL: the floors come from the store."""
    api.create_building(geo=True, size_m=(60.0, 50.0))
    key = api.key("hq", "device", "phone-1")
    assert _post(api, key, _batch(0)).json()["status"] == "applied"
    positions = api.client.get("/v1/buildings/hq/positions", headers=api.auth(api.operator)).json()
    t1 = _batch(1)["steps"][0]["t_ms"]
    far = _batch(1, landmarks=[{"kind": "fix", "t_ms": t1, "position": {"x_m": 1100.0, "y_m": 20.0}}])
    response = _post(api, key, far)
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert "outside the building" in detail
    assert "x 0..60 m" in detail
    assert "1000 m beyond" in detail
    # a GPS fix ~5.6 km north of the origin, through the geo-reference
    gps = _batch(1, landmarks=[{"kind": "gps", "t_ms": t1, "lat_deg": 47.65, "lon_deg": -122.3}])
    assert _post(api, key, gps).status_code == 422
    pinned = api.client.put(
        "/v1/buildings/hq/anchors/far",
        json={"type": "door", "position": {"x_m": 30.0, "y_m": -1051.0}},
        headers=api.auth(api.operator),
    )
    assert pinned.status_code == 422, pinned.text
    assert "the anchor at (30.0, -1051.0) m is outside the building" in pinned.json()["detail"]
    assert api.client.get("/v1/buildings/hq/anchors", headers=api.auth(api.operator)).json() == []
    after = api.client.get("/v1/buildings/hq/positions", headers=api.auth(api.operator)).json()
    assert after == positions
    # within the margin (an entrance, a car park) is fine, and the refused batch's id is still free
    near = _batch(1, landmarks=[{"kind": "fix", "t_ms": t1, "position": {"x_m": -900.0, "y_m": 20.0}}])
    body = _post(api, key, near).json()
    assert body["status"] == "applied", body
    assert body["estimate"]["position"]["x_m"] < -800.0
    door = api.client.put(
        "/v1/buildings/hq/anchors/door",
        json={"type": "door", "position": {"x_m": 60.0, "y_m": 1049.0}},
        headers=api.auth(api.operator),
    )
    assert door.status_code == 200, door.text


def test_without_floor_sizes_only_the_physical_bound_applies(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()  # no floors: the building's size is unknown
    key = api.key("hq", "device", "phone-1")
    t0 = _batch(0)["steps"][0]["t_ms"]
    body = _batch(0, landmarks=[{"kind": "fix", "t_ms": t0, "position": {"x_m": 5000.0, "y_m": 0.0}}])
    assert _post(api, key, body).json()["status"] == "applied"


def test_a_batch_from_the_future_is_refused_and_freezes_nobody(sqlite_api: Api) -> None:
    """Steps timed in 2099 had been accepted, and every later step of that user was then 'out of time
    order' forever."""
    api = sqlite_api
    api.create_building()
    key = api.key("hq", "device", "phone-1")
    assert _post(api, key, _batch(0)).json()["status"] == "applied"
    future = _batch(1)
    for step in future["steps"]:
        step["t_ms"] = 4_070_908_800_000 + step["t_ms"] % 10_000  # 2099
    response = _post(api, key, future)
    assert response.status_code == 422, response.text
    assert "ahead of the server's clock" in response.json()["detail"]
    soon = _batch(1)  # the same batch id, honest times
    body = _post(api, key, soon).json()
    assert body["status"] == "applied"
    assert not any("out of time order" in w for w in body["warnings"])
    # a phone clock a little ahead (under five minutes) is fine
    ahead = _batch(2)
    now_ms = int(time.time() * 1000)
    for k, step in enumerate(ahead["steps"]):
        step["t_ms"] = now_ms + 60_000 + k
    assert _post(api, key, ahead).json()["status"] == "applied"


def test_a_device_key_cannot_move_another_user(api: Api) -> None:
    """phone-3's key posting as user phone-2 had teleported phone-2. A device posts as its own id or as the
    user it has posted as; another user is 403 until an operator assigns the device to it. On SQLite and
    PostgreSQL: the binding lives in the store."""
    api.create_building()
    keys = {d: api.key("hq", "device", d) for d in ("phone-2", "phone-3")}
    for seq in range(2):
        for device, key in keys.items():
            assert _post(api, key, _batch(seq, device)).json()["status"] == "applied"
    before = api.client.get("/v1/buildings/hq/positions", headers=api.auth(api.operator)).json()
    t2 = _batch(2)["steps"][0]["t_ms"]
    teleport = _batch(2, "phone-3", user_id="phone-2")
    teleport["landmarks"] = [{"kind": "fix", "t_ms": t2, "position": {"x_m": 55.0, "y_m": 5.0}}]
    response = _post(api, keys["phone-3"], teleport)
    assert response.status_code == 403, response.text
    assert "phone-2" in response.json()["detail"]
    after = api.client.get("/v1/buildings/hq/positions", headers=api.auth(api.operator)).json()
    assert after == before
    # a new device may not take a user another device posts as either
    newcomer = api.key("hq", "device", "phone-9")
    assert _post(api, newcomer, _batch(0, "phone-9", user_id="phone-2")).status_code == 403
    # an operator hands phone-3 to user visitor-1: its batches are that user's, and no longer phone-3's
    response = api.client.put(
        "/v1/buildings/hq/devices/phone-3", json={"user_id": "visitor-1"}, headers=api.auth(api.operator)
    )
    assert response.status_code == 200, response.text
    assert response.json() == {"device_id": "phone-3", "user_id": "visitor-1"}
    refused = api.client.put(
        "/v1/buildings/hq/devices/phone-3", json={"user_id": "x"}, headers=api.auth(keys["phone-3"])
    )
    assert refused.status_code == 403
    moved = _batch(2, "phone-3", user_id="visitor-1")
    moved["landmarks"] = [{"kind": "fix", "t_ms": t2, "position": {"x_m": 20.0, "y_m": 5.0}}]
    body = _post(api, keys["phone-3"], moved).json()
    assert body["status"] == "applied", body
    assert body["estimate"]["user_id"] == "visitor-1"
    assert _post(api, keys["phone-3"], _batch(3, "phone-3", user_id="phone-3")).status_code == 200


def test_a_reinstalled_phone_posts_again_and_old_batches_never_apply(api: Api) -> None:
    """After a reinstall that starts seq at 1 again every batch had answered 'late', with no way out. With
    install_ms the new install's count starts again; a batch of the old install re-sent is late (a new id)
    or a duplicate (its id): never applied twice. On SQLite and PostgreSQL."""
    api.create_building()
    key = api.key("hq", "device", "phone-1")
    old, new = 1_767_225_600_000, 1_767_312_000_000

    def batch(seq: int, install: int) -> dict[str, Any]:
        body = _batch(seq)
        body["install_ms"] = install
        body["batch_id"] = f"{install}-{seq}"
        return body

    for seq in range(3):
        assert _post(api, key, batch(seq, old)).json()["status"] == "applied"
    for seq in (0, 1):  # reinstalled: from 0 again
        body = _post(api, key, batch(seq, new)).json()
        assert body["status"] == "applied", body
    assert _post(api, key, batch(2, old)).json()["status"] == "duplicate"  # re-sent as it was
    resent = batch(3, old)
    assert _post(api, key, resent).json()["status"] == "late"  # an old install's batch under a new id
    assert _post(api, key, batch(2, new)).json()["status"] == "applied"
