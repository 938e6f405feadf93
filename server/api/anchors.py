"""Operators query and edit a building's anchor map; GeoJSON export of anchors and recent tracks."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Response, status

from schemas.anchors import AnchorMergeIn, BuildingAnchor, GeoJsonExport, KnownAnchorIn
from schemas.common import MAX_TIME_MS, MIN_TIME_MS, Identifier
from server.api.contract import PROBLEMS, problems
from server.api.deps import Caller, DbSession, State
from server.api.links import BUILDING, SAME_BUILDING, link, links
from server.buildings.calls import DeleteAnchor, GetAnchor, ListAnchors, MergeAnchors, PinAnchor
from server.buildings.handles import BuildingHandle
from server.errors import ConflictError
from server.store import repositories as repo

router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["anchors"])


async def _handle(state: State, building_id: str) -> BuildingHandle:
    return await state.tracking.handle(building_id)


@router.get("/anchors", response_model=list[BuildingAnchor], responses=problems(403, 404, 503))
async def list_anchors(building_id: str, caller: Caller, state: State) -> list[BuildingAnchor]:
    """The building's shared anchor map: learned by the crowd, or pinned by operators."""
    caller.require_reader(building_id)
    building = await _handle(state, building_id)
    anchors = await building.ask(ListAnchors())
    return anchors


_NO_ANCHOR = (404, "No such building, or no live anchor of this id in it.")


@router.get("/anchors/{anchor_id}", response_model=BuildingAnchor, responses=problems(403, _NO_ANCHOR, 503))
async def get_anchor(building_id: str, anchor_id: Identifier, caller: Caller, state: State) -> BuildingAnchor:
    caller.require_reader(building_id)
    building = await _handle(state, building_id)
    anchor = await building.ask(GetAnchor(anchor_id))
    return anchor


_ANCHOR = f"{BUILDING}/anchors/{{anchor_id}}"
_THIS_ANCHOR = {"building_id": SAME_BUILDING, "anchor_id": "$response.body#/id"}
_ANCHOR_LINKS = links(
    200,
    GetAnchor=link("GET", _ANCHOR, "The anchor.", **_THIS_ANCHOR),
    DeleteAnchor=link("DELETE", _ANCHOR, "Delete the anchor.", **_THIS_ANCHOR),
)


@router.put(
    "/anchors/{anchor_id}",
    response_model=BuildingAnchor,
    responses={
        **problems(
            400,
            403,
            404,
            (409, "The anchor id was deleted or merged: pick a new one."),
            413,
            (422, PROBLEMS[422] + " A position outside the building's floors is refused."),
            503,
        ),
        **_ANCHOR_LINKS,
    },
)
async def put_known_anchor(
    building_id: str, anchor_id: Identifier, body: KnownAnchorIn, caller: Caller, state: State
) -> BuildingAnchor:
    """Pin an anchor at an exact position (operator key): a new known anchor, or a learned one made exact."""
    caller.require_operator(building_id)
    building = await _handle(state, building_id)
    anchor: BuildingAnchor
    anchor, messages = await building.ask(PinAnchor(anchor_id, body))
    building.publish(messages)
    return anchor


@router.delete(
    "/anchors/{anchor_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=problems(403, _NO_ANCHOR, 503),
)
async def delete_anchor(building_id: str, anchor_id: Identifier, caller: Caller, state: State) -> Response:
    caller.require_operator(building_id)
    building = await _handle(state, building_id)
    messages = await building.ask(DeleteAnchor(anchor_id))
    building.publish(messages)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post(
    "/anchors:merge",
    response_model=BuildingAnchor,
    responses={
        **problems(
            400, 403, 404, (409, "One of the anchors named is not live: nothing was merged."), 413, 422, 503
        ),
        **_ANCHOR_LINKS,
    },
)
async def merge_anchors(
    building_id: str, body: AnchorMergeIn, caller: Caller, state: State
) -> BuildingAnchor:
    """Merge anchors the crowd learned twice into the first one listed (operator key)."""
    caller.require_operator(building_id)
    building = await _handle(state, building_id)
    anchor: BuildingAnchor
    anchor, messages = await building.ask(MergeAnchors(tuple(body.anchor_ids)))
    building.publish(messages)
    return anchor


@router.get(
    "/export.geojson",
    response_model=GeoJsonExport,
    responses=problems(403, 404, (409, "The building has no geo-reference to export in WGS-84."), 503),
)
async def export_geojson(
    building_id: str,
    caller: Caller,
    state: State,
    session: DbSession,
    since_ms: Annotated[int, Query(ge=MIN_TIME_MS, le=MAX_TIME_MS)] = MIN_TIME_MS,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 20_000,
) -> GeoJsonExport:
    """Anchors as points and recent tracks as lines, in WGS-84 (needs the building's geo-reference)."""
    caller.require_reader(building_id)
    building = await _handle(state, building_id)
    geo = building.geo
    if geo is None:
        raise ConflictError(f"building {building_id!r} has no geo-reference; set one to export GeoJSON")
    anchors = await building.ask(ListAnchors())
    features: list[dict[str, Any]] = []
    for a in anchors:
        lat, lon = geo.to_wgs84(a.position.x_m, a.position.y_m)
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [lon, lat]},
                "properties": {"kind": "anchor", **a.model_dump(mode="json", exclude={"position"})},
            }
        )
    tracks: dict[str, list[list[float]]] = {}
    for row in repo.recent_tracks(session, building_id, since_ms, limit):
        lat, lon = geo.to_wgs84(row.x_m, row.y_m)
        tracks.setdefault(row.user_id, []).append([lon, lat])
    for user, coords in tracks.items():
        if len(coords) >= 2:
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "LineString", "coordinates": coords},
                    "properties": {"kind": "track", "user_id": user},
                }
            )
    return GeoJsonExport(features=features)
