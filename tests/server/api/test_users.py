"""``DELETE /v1/buildings/{id}/users/{user}``: an operator makes the server forget a user; dashboards are told
to drop it."""

from __future__ import annotations

from tests.server.api.test_api import _batch
from tests.server.conftest import Api


def test_a_forgotten_user_leaves_the_positions_history_and_live_view(api: Api) -> None:
    api.create_building()
    dashboard = api.key("hq", "dashboard")
    for device in ("phone-1", "phone-2"):
        key = api.key("hq", "device", device)
        for seq in range(3):
            r = api.client.post("/v1/buildings/hq/batches", json=_batch(seq, device), headers=api.auth(key))
            assert r.status_code == 200, r.text
    as_dashboard, as_operator = api.auth(dashboard), api.auth(api.operator)

    assert api.client.delete("/v1/buildings/hq/users/phone-1", headers=as_dashboard).status_code == 403
    with api.client.websocket_connect(f"/v1/buildings/hq/live?token={dashboard}") as live:
        forgotten = api.client.delete("/v1/buildings/hq/users/phone-1", headers=as_operator)
        assert forgotten.status_code == 204, forgotten.text
        messages = [live.receive_json() for _ in range(1)]
    assert messages == [{"type": "user_forgotten", "user_id": "phone-1"}]

    positions = api.client.get("/v1/buildings/hq/positions", headers=as_dashboard).json()
    assert [p["user_id"] for p in positions] == ["phone-2"]
    history = api.client.get("/v1/buildings/hq/users/phone-1/positions", headers=as_dashboard)
    assert history.json() == []
    assert len(api.client.get("/v1/buildings/hq/users/phone-2/positions", headers=as_dashboard).json()) == 2

    again = api.client.delete("/v1/buildings/hq/users/phone-1", headers=as_operator)
    assert again.status_code == 404
    assert again.headers["content-type"] == "application/problem+json"
    assert "no user 'phone-1'" in again.json()["detail"]
    assert api.client.delete("/v1/buildings/nowhere/users/phone-2", headers=as_operator).status_code == 404
