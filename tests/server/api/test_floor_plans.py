"""Floor plans through the API: uploaded in the local frame or WGS-84, validated with clear errors, stored,
served, and weighing the tracked floor's steps, also after a restart. On SQLite and PostgreSQL."""

from __future__ import annotations

import contextlib
import copy
from typing import Any

import pytest

from schemas.floor_plans import FLOOR_PLAN_EXAMPLE
from server.app import create_app
from tests.server.conftest import Api

PLAN = "/v1/buildings/hq/floors/0/plan"


def _tracked_plan(api: Api) -> object:
    """The plan the building's tracker weighs steps with (None: none)."""
    worker: Any = api.client.app.state.crowdslam.tracking.handles["hq"]  # type: ignore[attr-defined]
    return worker.host.tracker.filters.floor_plans.get(0)


def test_a_plan_is_stored_served_and_tracked(api: Api) -> None:
    api.create_building(size_m=(60.0, 50.0))
    op = api.auth(api.operator)
    assert api.client.get(PLAN, headers=op).status_code == 404
    put = api.client.put(PLAN, json=FLOOR_PLAN_EXAMPLE, headers=op)
    assert put.status_code == 200, put.text
    assert put.json() == FLOOR_PLAN_EXAMPLE | {"features": put.json()["features"]}
    got = api.client.get(PLAN, headers=api.auth(api.key("hq", "dashboard")))
    assert got.status_code == 200
    assert got.json() == put.json()
    plan: Any = _tracked_plan(api)
    assert plan is not None
    assert plan.walls.shape == (5, 4)  # the cafe's four sides and one wall
    assert plan.walkable([[30.0, 25.0], [70.0, 25.0]]).tolist() == [True, False]
    # a restart loads the tracked floor's plan again
    with contextlib.ExitStack() as stack:
        from fastapi.testclient import TestClient

        again = stack.enter_context(TestClient(create_app(api.settings)))
        again.get("/v1/buildings/hq/anchors", headers=op)  # loads the building
        worker: Any = again.app.state.crowdslam.tracking.handles["hq"]  # type: ignore[attr-defined]
        assert worker.host.tracker.filters.floor_plans[0].walls.shape == (5, 4)


def test_a_wgs84_plan_is_placed_by_the_geo_reference(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building(geo=True, size_m=(60.0, 50.0))
    op = api.auth(api.operator)
    plan = copy.deepcopy(FLOOR_PLAN_EXAMPLE)
    plan["frame"] = "wgs84"
    # a square of ~11 x 11 m north-east of the origin (47.6 N, 122.3 W)
    square = [[-122.3, 47.6], [-122.29985, 47.6], [-122.29985, 47.6001], [-122.3, 47.6001], [-122.3, 47.6]]
    plan["features"] = [
        {
            "type": "Feature",
            "properties": {"kind": "walkable"},
            "geometry": {"type": "Polygon", "coordinates": [square]},
        }
    ]
    put = api.client.put(PLAN, json=plan, headers=op)
    assert put.status_code == 200, put.text
    assert put.json()["frame"] == "local"
    ring = put.json()["features"][0]["geometry"]["coordinates"][0]
    assert ring[0] == [0.0, 0.0]
    # the building's frame is rotated by 0.3 rad: the far corner is ~15.8 m from the origin either way
    assert abs((ring[2][0] ** 2 + ring[2][1] ** 2) ** 0.5 - 15.8) < 0.3


@pytest.mark.parametrize(
    ("change", "status", "says"),
    [
        (lambda p: p["features"][0]["geometry"]["coordinates"][0].pop(), 422, "end at its first position"),
        (lambda p: p["features"][0]["properties"].update(kind="floor"), 422, "kind"),
        (
            lambda p: p["features"].append(
                {
                    "type": "Feature",
                    "properties": {"kind": "walkable"},
                    "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]},
                }
            ),
            422,
            "must be a Polygon",
        ),
        (
            lambda p: p["features"][2]["geometry"]["coordinates"].append([5000.0, 0.0]),
            422,
            "outside the building",
        ),
        (lambda p: p.update(frame="wgs84"), 422, "no geo-reference"),
        (lambda p: p.update(features=[]), 422, "features"),
    ],
)
def test_bad_plans_are_refused_with_what_is_wrong(
    sqlite_api: Api, change: Any, status: int, says: str
) -> None:
    api = sqlite_api
    api.create_building(size_m=(60.0, 50.0))
    plan = copy.deepcopy(FLOOR_PLAN_EXAMPLE)
    change(plan)
    response = api.client.put(PLAN, json=plan, headers=api.auth(api.operator))
    assert response.status_code == status, response.text
    assert says in response.text
    assert api.client.get(PLAN, headers=api.auth(api.operator)).status_code == 404  # nothing stored


def test_who_may_upload_where(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building(size_m=(60.0, 50.0))
    dashboard = api.auth(api.key("hq", "dashboard"))
    assert api.client.put(PLAN, json=FLOOR_PLAN_EXAMPLE, headers=dashboard).status_code == 403
    missing = api.client.put(
        "/v1/buildings/hq/floors/3/plan", json=FLOOR_PLAN_EXAMPLE, headers=api.auth(api.operator)
    )
    assert missing.status_code == 404
    assert "its floors: 0" in missing.json()["detail"]
    huge = b'{"type": "FeatureCollection", "features": [' + b" " * (api.settings.max_plan_bytes + 1)
    refused = api.client.put(
        PLAN, content=huge, headers={**api.auth(api.operator), "Content-Type": "application/json"}
    )
    assert refused.status_code == 413
    assert _tracked_plan(api) is None
