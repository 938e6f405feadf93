"""SignalSLAM signal maps of a building, built from its recordings in a separate process."""

from __future__ import annotations

from fastapi import APIRouter, status
from fastapi.responses import FileResponse

from schemas.signal_maps import SignalMapJob
from server.api.contract import problems
from server.api.deps import Caller, State
from server.api.links import BUILDING, SAME_BUILDING, link, links
from server.buildings.calls import ConversionContext, FlushRecording

router = APIRouter(prefix="/v1/buildings/{building_id}/signal-maps", tags=["signal maps"])


@router.post(
    "",
    response_model=SignalMapJob,
    status_code=status.HTTP_202_ACCEPTED,
    responses={
        **problems(
            403,
            404,
            (409, "The building has no recordings to build from, or recording is switched off."),
            (429, "As many builds as allowed are queued or running: start this one when one has ended."),
            503,
        ),
        **links(
            202,
            GetBuild=link(
                "GET",
                f"{BUILDING}/signal-maps/{{job_id}}",
                "The build's status.",
                building_id=SAME_BUILDING,
                job_id="$response.body#/id",
            ),
        ),
    },
)
async def start_signal_map_build(building_id: str, caller: Caller, state: State) -> SignalMapJob:
    """Start a build over every recording of the building (operator key). Walks between two landmarks
    (position fixes, known-anchor readings, tags with a position) are optimised jointly with WiFi signal
    edges; poll the job, then fetch its files (signal maps as PNG and JSON grids, the 5 m fingerprint
    database, the optimised trajectories)."""
    caller.require_operator(building_id)
    building = await state.tracking.handle(building_id)
    await building.ask(FlushRecording())  # the build reads every batch recorded until now
    ctx = await building.ask(ConversionContext())
    return state.signal_maps.start(ctx)


@router.get("", response_model=list[SignalMapJob], responses=problems(403, 404, 503))
async def list_signal_map_builds(building_id: str, caller: Caller, state: State) -> list[SignalMapJob]:
    """The building's builds (dashboard or operator key: dashboards overlay finished maps)."""
    caller.require_reader(building_id)
    await state.tracking.handle(building_id)  # 404 for an unknown building
    return state.signal_maps.list(building_id)


@router.get(
    "/{job_id}",
    response_model=SignalMapJob,
    responses=problems(403, (404, "No such building, or no build of this id for it."), 503),
)
async def get_signal_map_build(building_id: str, job_id: str, caller: Caller, state: State) -> SignalMapJob:
    caller.require_reader(building_id)
    await state.tracking.handle(building_id)  # 404 for an unknown building
    return state.signal_maps.get(building_id, job_id)


@router.get(
    "/{job_id}/files/{name}",
    response_class=FileResponse,
    responses={
        200: {
            "description": "The file.",
            "content": {
                "image/png": {"schema": {"type": "string", "format": "binary"}},
                "application/json": {"schema": {}},
                "application/geo+json": {"schema": {}},
            },
        },
        **problems(403, (404, "No such building, build, or file of a finished build."), 503),
    },
)
async def get_signal_map_file(
    building_id: str, job_id: str, name: str, caller: Caller, state: State
) -> FileResponse:
    """One output of a finished build (``image/png`` or ``application/json``; dashboard or operator key)."""
    caller.require_reader(building_id)
    await state.tracking.handle(building_id)
    path = state.signal_maps.file(building_id, job_id, name)
    media = {".png": "image/png", ".geojson": "application/geo+json"}.get(path.suffix, "application/json")
    return FileResponse(path, media_type=media)
