"""Zones: operators draw them on a floor; dashboards read who is in them now, at a past time, and their
visits."""

from __future__ import annotations

import asyncio
import time
from typing import Annotated

from fastapi import APIRouter, Query, Response, status

from schemas.common import MAX_TIME_MS, MIN_TIME_MS, Identifier
from schemas.zones import MAX_VISITS, Zone, ZoneIn, ZoneOccupancy, ZoneVisit
from server.api.contract import PROBLEMS, problems
from server.api.deps import Caller, State
from server.api.links import BUILDING, SAME_BUILDING, link, links
from server.buildings.calls import DeleteZone, PutZone
from server.errors import NotFoundError
from server.ingestion.zones import wire_zone
from server.store import repositories as repo
from server.store.models import ZoneVisitRow

router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["zones"])

_ZONE = f"{BUILDING}/zones/{{zone_id}}"
_THIS_ZONE = {"building_id": SAME_BUILDING, "zone_id": "$response.body#/id"}
_NO_BUILDING = (404, "No such building.")
_NO_ZONE = (404, "No such building, or no zone of this id in it.")


def _visit(row: ZoneVisitRow) -> ZoneVisit:
    return ZoneVisit(
        zone_id=row.zone_id,
        user_id=row.user_id,
        entered_ms=row.entered_ms,
        left_ms=row.left_ms,
        seconds=None if row.left_ms is None else (row.left_ms - row.entered_ms) / 1000.0,
        dwelled=row.dwelled_ms is not None,
    )


@router.get("/zones", response_model=list[Zone], responses=problems(403, _NO_BUILDING))
async def list_zones(building_id: str, caller: Caller, state: State) -> list[Zone]:
    """The building's zones, each with the users inside it now (dashboard or operator key)."""
    caller.require_reader(building_id)

    def query() -> list[Zone]:
        with state.sessions() as session:
            if repo.get_building(session, building_id) is None:
                raise NotFoundError(f"no building {building_id!r}")
            counts = repo.zone_occupancy(session, building_id)
            return [wire_zone(z, counts.get(z.id, 0)) for z in repo.list_zones(session, building_id)]

    return await asyncio.to_thread(query)


@router.get("/zones/occupancy", response_model=ZoneOccupancy, responses=problems(403, _NO_BUILDING, 422))
async def get_zone_occupancy(
    building_id: str,
    caller: Caller,
    state: State,
    at_ms: Annotated[
        int | None,
        Query(
            alias="at",
            ge=MIN_TIME_MS,
            le=MAX_TIME_MS,
            description="Epoch milliseconds; now when absent. From the stored visits, which the server keeps "
            "as long as the position history (`CROWDSLAM_POSITION_HISTORY_DAYS`).",
        ),
    ] = None,
) -> ZoneOccupancy:
    """Users inside each zone at a time (dashboard or operator key): every zone, 0 where nobody was."""
    caller.require_reader(building_id)

    def query() -> ZoneOccupancy:
        with state.sessions() as session:
            if repo.get_building(session, building_id) is None:
                raise NotFoundError(f"no building {building_id!r}")
            counts = repo.zone_occupancy(session, building_id, at_ms)
            ids = [z.id for z in repo.list_zones(session, building_id)]
        return ZoneOccupancy(
            at_ms=int(time.time() * 1000) if at_ms is None else at_ms,
            zones={z: counts.get(z, 0) for z in ids},
        )

    return await asyncio.to_thread(query)


@router.get("/zones/{zone_id}", response_model=Zone, responses=problems(403, _NO_ZONE))
async def get_zone(building_id: str, zone_id: Identifier, caller: Caller, state: State) -> Zone:
    """One zone, with the users inside it now (dashboard or operator key)."""
    caller.require_reader(building_id)

    def query() -> Zone:
        with state.sessions() as session:
            zone = repo.get_zone(session, building_id, zone_id)
            if zone is None:
                raise NotFoundError(f"no zone {zone_id!r} in building {building_id!r}")
            return wire_zone(zone, repo.zone_occupancy(session, building_id).get(zone_id, 0))

    return await asyncio.to_thread(query)


@router.put(
    "/zones/{zone_id}",
    response_model=Zone,
    responses={
        **problems(
            400,
            403,
            (404, "No such building, or no such floor in it."),
            413,
            (
                422,
                PROBLEMS[422] + " An outline that crosses itself, encloses no area, or lies outside the "
                "building's floors is refused, as is a building's zone beyond the most it may hold.",
            ),
            503,
        ),
        **links(
            200,
            GetZone=link("GET", _ZONE, "The zone.", **_THIS_ZONE),
            ZoneVisits=link("GET", f"{_ZONE}/visits", "Its visits.", **_THIS_ZONE),
            DeleteZone=link("DELETE", _ZONE, "Delete it.", **_THIS_ZONE),
        ),
    },
)
async def put_zone(building_id: str, zone_id: Identifier, body: ZoneIn, caller: Caller, state: State) -> Zone:
    """Draw or redraw a zone on a floor (operator key): a polygon in the building's local frame, one ring
    without holes. Users' entries, exits and dwells are decided from the next batch on, from each one's
    particles: a user enters when it is inside with probability 0.8, and leaves when that falls to 0.2.
    Redrawing keeps the zone's visits."""
    caller.require_operator(building_id)
    building = await state.tracking.handle(building_id)
    zone = await building.ask(PutZone(zone_id, body))
    return zone


@router.delete(
    "/zones/{zone_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=problems(403, _NO_ZONE, 503),
)
async def delete_zone(building_id: str, zone_id: Identifier, caller: Caller, state: State) -> Response:
    """Delete a zone and its visits (operator key)."""
    caller.require_operator(building_id)
    building = await state.tracking.handle(building_id)
    await building.ask(DeleteZone(zone_id))
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/zones/{zone_id}/visits", response_model=list[ZoneVisit], responses=problems(403, _NO_ZONE, 422))
async def list_zone_visits(
    building_id: str,
    zone_id: Identifier,
    caller: Caller,
    state: State,
    since_ms: Annotated[
        int, Query(alias="since", ge=MIN_TIME_MS, le=MAX_TIME_MS, description="Epoch milliseconds.")
    ] = MIN_TIME_MS,
    until_ms: Annotated[
        int, Query(alias="until", ge=MIN_TIME_MS, le=MAX_TIME_MS, description="Epoch milliseconds.")
    ] = MAX_TIME_MS,
    limit: Annotated[int, Query(ge=1, le=MAX_VISITS)] = 1_000,
) -> list[ZoneVisit]:
    """The zone's visits that overlap [since, until), in the order they began (dashboard or operator key):
    who, when it entered and left (null: inside still), and whether its dwell fired."""
    caller.require_reader(building_id)

    def query() -> list[ZoneVisit]:
        with state.sessions() as session:
            if repo.get_zone(session, building_id, zone_id) is None:
                raise NotFoundError(f"no zone {zone_id!r} in building {building_id!r}")
            rows = repo.zone_visits(session, building_id, zone_id, since_ms, until_ms, limit)
            return [_visit(r) for r in rows]

    return await asyncio.to_thread(query)
