"""Dashboards read positions: every user's latest estimate, and one user's history. A phone reads its own."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from schemas.api import DevicePosition
from schemas.common import MAX_TIME_MS, MIN_TIME_MS, Identifier, Position
from schemas.estimates import Estimate, EstimateSource
from server.api.contract import PROBLEMS, problems
from server.api.deps import Caller, DbSession
from server.errors import InvalidInputError, NotFoundError
from server.store import repositories as repo
from server.store.models import LatestPositionRow, PositionSnapshotRow

router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["positions"])


def estimate_from_row(row: PositionSnapshotRow | LatestPositionRow) -> Estimate:
    return Estimate(
        building_id=row.building_id,
        user_id=row.user_id,
        device_id=row.device_id,
        t_ms=row.t_ms,
        position=Position(x_m=row.x_m, y_m=row.y_m),
        covariance_m2=[[row.cov_xx, row.cov_xy], [row.cov_xy, row.cov_yy]],
        heading_rad=row.heading_rad,
        floor=row.floor,
        floor_probability=row.floor_probability,
        source=EstimateSource(row.source),
    )


@router.get("/positions", response_model=list[Estimate], responses=problems(403, 404))
def list_positions(
    building_id: str,
    caller: Caller,
    session: DbSession,
    at_ms: Annotated[
        int | None,
        Query(
            ge=MIN_TIME_MS,
            le=MAX_TIME_MS,
            description="The building as it was then: each user's newest stored estimate within "
            "`window_ms` before it (from the position history, which the server keeps "
            "`CROWDSLAM_POSITION_HISTORY_DAYS`).",
        ),
    ] = None,
    window_ms: Annotated[int, Query(ge=1, le=3_600_000)] = 30_000,
) -> list[Estimate]:
    """Every user's latest estimate (dashboard or operator key), or with ``at_ms`` as it was then."""
    caller.require_reader(building_id)
    if repo.get_building(session, building_id) is None:
        raise NotFoundError(f"no building {building_id!r}")
    if at_ms is not None:
        return [estimate_from_row(r) for r in repo.positions_at(session, building_id, at_ms, window_ms)]
    return [estimate_from_row(r) for r in repo.latest_positions(session, building_id)]


@router.get(
    "/users/{user_id}/positions",
    response_model=list[Estimate],
    responses=problems(403, 404, (422, PROBLEMS[422] + " `since_ms` after `until_ms` is refused.")),
)
def get_user_history(
    building_id: str,
    user_id: str,
    caller: Caller,
    session: DbSession,
    since_ms: Annotated[int, Query(ge=MIN_TIME_MS, le=MAX_TIME_MS)] = MIN_TIME_MS,
    until_ms: Annotated[int, Query(ge=MIN_TIME_MS, le=MAX_TIME_MS)] = MAX_TIME_MS,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1_000,
) -> list[Estimate]:
    """One user's estimates in a time range, oldest first."""
    caller.require_reader(building_id)
    if since_ms > until_ms:
        raise InvalidInputError("since_ms must not be after until_ms")
    if repo.get_building(session, building_id) is None:
        raise NotFoundError(f"no building {building_id!r}")
    rows = repo.position_history(session, building_id, user_id, since_ms, until_ms, limit)
    return [estimate_from_row(r) for r in rows]


@router.get(
    "/devices/{device_id}/position",
    response_model=DevicePosition,
    responses=problems(403, 404),
)
def get_device_position(
    building_id: str, device_id: Identifier, caller: Caller, session: DbSession
) -> DevicePosition:
    """The user a device posts as and that user's latest estimate: its own device's with a device key (a phone
    shows itself after a reload), any device's with a dashboard or operator key. Until the device has posted
    (``user_id`` null) or its user is placed (``estimate`` null) it says so; the receipt of each applied
    batch carries the same estimate."""
    caller.require_own_device(building_id, device_id)
    if repo.get_building(session, building_id) is None:
        raise NotFoundError(f"no building {building_id!r}")
    user_id = repo.device_user(session, building_id, device_id)
    rows = [] if user_id is None else repo.latest_positions_of(session, building_id, [user_id])
    estimate = estimate_from_row(rows[0]) if rows else None
    return DevicePosition(device_id=device_id, user_id=user_id, estimate=estimate)
