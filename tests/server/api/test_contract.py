"""The spec says what the server answers: readable, unique operation ids; every error as
``application/problem+json``; the problems every operation can answer; RFC 3339 timestamps; a 405 that
names every method of its path."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from server.app import create_app
from server.errors import PROBLEM_MEDIA_TYPE
from server.settings import Settings
from tests.server.conftest import Api


def _operations(spec: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    return [(path, method, op) for path, item in spec["paths"].items() for method, op in item.items()]


OPERATION_IDS = {
    "get_health",
    "get_metrics",
    "get_current_key",
    "list_buildings",
    "create_building",
    "get_building",
    "create_key",
    "list_keys",
    "revoke_key",
    "assign_device",
    "get_device_position",
    "put_floor_plan",
    "get_floor_plan",
    "list_floor_plans",
    "post_batch",
    "list_positions",
    "get_user_history",
    "forget_user",
    "list_anchors",
    "get_anchor",
    "put_known_anchor",
    "delete_anchor",
    "merge_anchors",
    "export_geojson",
    "list_zones",
    "get_zone",
    "put_zone",
    "delete_zone",
    "list_zone_visits",
    "get_zone_occupancy",
    "put_webhook",
    "list_webhooks",
    "delete_webhook",
    "list_webhook_deliveries",
    "start_signal_map_build",
    "list_signal_map_builds",
    "get_signal_map_build",
    "get_signal_map_file",
}
"""Generated clients name their methods after these: a rename breaks every client, so it is a decision."""


def test_operation_ids_are_stable_readable_names(sqlite_api: Api) -> None:
    spec = sqlite_api.client.get("/openapi.json").json()
    ids = [op["operationId"] for _, _, op in _operations(spec)]
    assert len(ids) == len(set(ids))
    assert set(ids) == OPERATION_IDS


def test_every_error_is_a_problem_and_every_operation_lists_its_statuses(sqlite_api: Api) -> None:
    spec = sqlite_api.client.get("/openapi.json").json()
    problem = {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}}
    assert "HTTPValidationError" not in spec["components"]["schemas"]
    for path, method, op in _operations(spec):
        where = f"{method.upper()} {path}"
        statuses = {int(s) for s in op["responses"]}
        for status, response in op["responses"].items():
            if int(status) >= 400:
                assert response["content"] == problem, where
                assert response["description"], where
        secured = bool(op.get("security"))
        assert secured == (path not in ("/healthz", "/metrics")), where
        if secured:
            assert 401 in statuses, where
            assert op["responses"]["401"]["headers"]["WWW-Authenticate"]["required"], where
        if "{building_id}" in path:
            assert {403, 404} <= statuses, where
        if "requestBody" in op:
            assert {400, 413, 422} <= statuses, where
        if 429 in statuses:
            assert op["responses"]["429"]["headers"]["Retry-After"]["required"], where
    batch = spec["paths"]["/v1/buildings/{building_id}/batches"]["post"]
    assert {400, 401, 403, 404, 413, 422, 429, 500, 503} <= {int(s) for s in batch["responses"]}
    assert batch["requestBody"]["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/SensorBatch"
    }


def test_metrics_are_documented_as_the_server_serves_them(tmp_path: Any) -> None:
    def metrics(need_key: bool) -> dict[str, Any]:
        settings = Settings(
            data_dir=tmp_path, database_url=f"sqlite:///{tmp_path}/db.sqlite3", metrics_need_key=need_key
        )
        operation: dict[str, Any] = create_app(settings).openapi()["paths"]["/metrics"]["get"]
        return operation

    open_ = metrics(False)
    assert "security" not in open_
    assert set(open_["responses"]) == {"200"}
    keyed = metrics(True)
    assert keyed["security"]
    assert {"200", "401", "403"} <= set(keyed["responses"])
    assert "text/plain; version=0.0.4" in keyed["responses"]["200"]["content"]


def test_timestamps_carry_their_offset(api: Api) -> None:
    api.create_building()
    api.key("hq", "dashboard")
    keys = api.client.get("/v1/buildings/hq/keys", headers=api.auth(api.operator)).json()
    assert keys
    for key in keys:
        assert key["created_at"].endswith("Z"), key
        assert datetime.fromisoformat(key["created_at"]).utcoffset() is not None


def test_a_405_names_every_method_its_path_takes(sqlite_api: Api) -> None:
    sqlite_api.create_building()
    for path, methods in (
        ("/v1/buildings", "GET, HEAD, POST"),
        ("/v1/buildings/hq/keys", "GET, HEAD, POST"),
        ("/v1/buildings/hq/anchors/a1", "DELETE, GET, HEAD, PUT"),
        ("/v1/buildings/hq/anchors:merge", "POST"),
    ):
        response = sqlite_api.client.request("TRACE", path, headers=sqlite_api.auth(sqlite_api.operator))
        assert response.status_code == 405, path
        assert response.headers["allow"] == methods, path
        assert response.headers["content-type"] == PROBLEM_MEDIA_TYPE
