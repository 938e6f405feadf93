"""Buildings, their floors and geo-reference; a building's keys (minted, listed, revoked) and devices."""

from __future__ import annotations

import asyncio
from typing import Annotated

from fastapi import APIRouter, Path, Response, status

from schemas.api import DeviceKeyIn, KeyCreated, KeyCreateIn, KeyInfo, KeyScope
from schemas.buildings import Building, DeviceAssignment, DeviceAssignmentIn, Floor, GeoReference
from schemas.common import Identifier
from schemas.floor_plans import FloorPlan
from server.api.contract import problems
from server.api.deps import Caller, DbSession, State
from server.api.links import BUILDING, SAME_BUILDING, link, links
from server.auth import mint_key
from server.buildings.calls import AssignDevice, PutFloorPlan
from server.errors import ConflictError, InvalidInputError, NotFoundError
from server.store import repositories as repo
from server.store.models import ApiKeyRow, BuildingRow, FloorRow

router = APIRouter(prefix="/v1/buildings", tags=["buildings"])


def _building(row: BuildingRow, floors: list[FloorRow]) -> Building:
    geo = None
    if row.origin_lat_deg is not None and row.origin_lon_deg is not None:
        geo = GeoReference(
            origin_lat_deg=row.origin_lat_deg,
            origin_lon_deg=row.origin_lon_deg,
            rotation_rad=row.rotation_rad,
        )
    return Building(
        id=row.id,
        name=row.name,
        geo_reference=geo,
        floors=[
            Floor(
                level=f.level, name=f.name, elevation_m=f.elevation_m, width_m=f.width_m, height_m=f.height_m
            )
            for f in floors
        ],
    )


_NEW_BUILDING = "$response.body#/id"


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=Building,
    responses={
        **problems(400, 403, (409, "A building with this id exists."), 413, 422),
        **links(
            201,
            GetBuilding=link("GET", BUILDING, "The building created.", building_id=_NEW_BUILDING),
            CreateKey=link("POST", f"{BUILDING}/keys", "Mint its keys.", building_id=_NEW_BUILDING),
            ListKeys=link("GET", f"{BUILDING}/keys", "Its keys.", building_id=_NEW_BUILDING),
            PinAnchor=link(
                "PUT", f"{BUILDING}/anchors/{{anchor_id}}", "Pin a known anchor.", building_id=_NEW_BUILDING
            ),
            ListAnchors=link("GET", f"{BUILDING}/anchors", "Its anchor map.", building_id=_NEW_BUILDING),
            LatestPositions=link("GET", f"{BUILDING}/positions", "Its users.", building_id=_NEW_BUILDING),
            FloorPlans=link(
                "GET", f"{BUILDING}/floor-plans", "Its floors with a plan.", building_id=_NEW_BUILDING
            ),
            StartSignalMap=link(
                "POST", f"{BUILDING}/signal-maps", "Build its signal maps.", building_id=_NEW_BUILDING
            ),
        ),
    },
)
def create_building(body: Building, caller: Caller, session: DbSession) -> Building:
    """Create a building (operator key). Its id is permanent; a taken id is 409."""
    caller.require_operator(body.id)
    if len({f.level for f in body.floors}) != len(body.floors):
        raise InvalidInputError("floor levels must be distinct")
    geo = body.geo_reference
    row = BuildingRow(
        id=body.id,
        name=body.name,
        origin_lat_deg=geo.origin_lat_deg if geo else None,
        origin_lon_deg=geo.origin_lon_deg if geo else None,
        rotation_rad=geo.rotation_rad if geo else 0.0,
    )
    floors = [
        FloorRow(
            level=f.level, name=f.name, elevation_m=f.elevation_m, width_m=f.width_m, height_m=f.height_m
        )
        for f in body.floors
    ]
    if not repo.insert_building(session, row, floors):
        raise ConflictError(f"building {body.id!r} already exists")
    session.commit()
    return body


@router.get("", response_model=list[Building])
def list_buildings(caller: Caller, session: DbSession) -> list[Building]:
    """The buildings this key can see."""
    ids = None if caller.building_id is None else [caller.building_id]
    return [_building(b, repo.list_floors(session, b.id)) for b in repo.list_buildings(session, ids)]


@router.get("/{building_id}", response_model=Building, responses=problems(403, 404))
def get_building(building_id: str, caller: Caller, session: DbSession) -> Building:
    """The building, its geo-reference and floors (any key of the building)."""
    caller.require_member(building_id)
    row = repo.get_building(session, building_id)
    if row is None:
        raise NotFoundError(f"no building {building_id!r}")
    return _building(row, repo.list_floors(session, building_id))


@router.post(
    "/{building_id}/keys",
    status_code=status.HTTP_201_CREATED,
    response_model=KeyCreated,
    responses={
        **problems(400, 403, 404, 413, 422),
        **links(
            201,
            RevokeKey=link(
                "DELETE",
                f"{BUILDING}/keys/{{prefix}}",
                "Revoke the key minted.",
                building_id=SAME_BUILDING,
                prefix="$response.body#/prefix",
            ),
            AssignDevice=link(
                "PUT",
                f"{BUILDING}/devices/{{device_id}}",
                "Assign the key's device to a user.",
                building_id=SAME_BUILDING,
                device_id="$response.body#/device_id",
            ),
        ),
    },
)
def create_key(building_id: str, body: KeyCreateIn, caller: Caller, session: DbSession) -> KeyCreated:
    """Mint a device, dashboard or building operator key (operator key). The secret is shown only here."""
    caller.require_operator(building_id)
    if repo.get_building(session, building_id) is None:
        raise NotFoundError(f"no building {building_id!r}")
    secret, prefix = mint_key(session, body.scope, building_id, body.device_id)
    session.commit()
    return KeyCreated(
        key=secret,
        prefix=prefix,
        scope=body.scope,
        building_id=building_id,
        device_id=body.device_id if isinstance(body, DeviceKeyIn) else None,
    )


def key_info(row: ApiKeyRow) -> KeyInfo:
    return KeyInfo(
        prefix=row.prefix,
        scope=KeyScope(row.scope),
        building_id=row.building_id,
        device_id=row.device_id,
        created_at=row.created_at,
        last_used_at=row.last_used_at,
        revoked_at=row.revoked_at,
    )


@router.get("/{building_id}/keys", response_model=list[KeyInfo], responses=problems(403, 404))
async def list_keys(building_id: str, caller: Caller, state: State) -> list[KeyInfo]:
    """The building's keys, revoked ones included, with when each was last used (operator key). Never a
    secret."""
    caller.require_operator(building_id)
    used = state.keys.take_used()  # what this process saw since its last revalidation, written first

    def query() -> list[KeyInfo]:
        with state.sessions.begin() as session:
            if repo.get_building(session, building_id) is None:
                raise NotFoundError(f"no building {building_id!r}")
            repo.touch_keys(session, used)
            return [key_info(row) for row in repo.list_keys(session, building_id)]

    return await asyncio.to_thread(query)


@router.delete(
    "/{building_id}/keys/{prefix}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=problems(403, (404, "No such building, or no live key with this prefix in it.")),
)
async def revoke_key(building_id: str, prefix: str, caller: Caller, state: State) -> Response:
    """Revoke a key of the building by its prefix (operator key): refused at once by this server, and by
    every other within ``CROWDSLAM_KEY_CACHE_S``."""
    caller.require_operator(building_id)

    def revoke() -> list[int]:
        with state.sessions.begin() as session:
            return repo.revoke_keys(session, building_id, prefix)

    revoked = await asyncio.to_thread(revoke)
    if not revoked:
        raise NotFoundError(f"no live key {prefix!r} in building {building_id!r}")
    state.keys.forget(revoked)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.put(
    "/{building_id}/devices/{device_id}",
    response_model=DeviceAssignment,
    responses=problems(400, 403, 404, 413, 422, 503),
)
async def assign_device(
    building_id: str, device_id: Identifier, body: DeviceAssignmentIn, caller: Caller, state: State
) -> DeviceAssignment:
    """Assign a device to a user (operator key): the device's batches are that user's from now on, and the
    device may no longer post as the user it posted as before (a phone handed to someone else)."""
    caller.require_operator(building_id)
    building = await state.tracking.handle(building_id)
    await building.ask(AssignDevice(device_id, body.user_id))
    return DeviceAssignment(device_id=device_id, user_id=body.user_id)


Level = Annotated[int, Path(ge=-20, le=200, description="The floor's level (0 is the ground floor).")]


@router.put(
    "/{building_id}/floors/{level}/plan",
    response_model=FloorPlan,
    responses=problems(400, 403, 404, 413, 422, 503),
)
async def put_floor_plan(
    building_id: str, level: Level, body: FloorPlan, caller: Caller, state: State
) -> FloorPlan:
    """Upload a floor's plan (operator key): GeoJSON features of kind ``walkable`` (the floor's outline),
    ``obstacle`` (shops, rooms: their outlines are walls with unknown doors) and ``wall``, in the local frame
    or in WGS-84 through the building's geo-reference, within the building's extent. It replaces the floor's
    plan; the plan of floor 0, where users are tracked, weighs their steps from the next batch on. Answers the
    plan as stored, in the local frame."""
    caller.require_operator(building_id)
    building = await state.tracking.handle(building_id)
    plan = await building.ask(PutFloorPlan(level, body))
    return plan


@router.get("/{building_id}/floor-plans", response_model=list[int], responses=problems(403, 404))
def list_floor_plans(building_id: str, caller: Caller, session: DbSession) -> list[int]:
    """The levels whose floor has a plan (any key of the building)."""
    caller.require_member(building_id)
    if repo.get_building(session, building_id) is None:
        raise NotFoundError(f"no building {building_id!r}")
    return repo.floor_plan_levels(session, building_id)


@router.get(
    "/{building_id}/floors/{level}/plan",
    response_model=FloorPlan,
    responses=problems(403, (404, "No such building, or its floor has no plan.")),
)
async def get_floor_plan(building_id: str, level: Level, caller: Caller, state: State) -> Response:
    """The floor's plan in the local frame (any key of the building: a phone draws itself on it)."""
    caller.require_member(building_id)

    def query() -> str | None:
        with state.sessions() as session:
            if repo.get_building(session, building_id) is None:
                raise NotFoundError(f"no building {building_id!r}")
            return repo.floor_plan(session, building_id, level)

    text = await asyncio.to_thread(query)
    if text is None:
        raise NotFoundError(f"floor {level} of building {building_id!r} has no plan")
    return Response(text, media_type="application/json")
