"""Liveness and Prometheus metrics."""

from __future__ import annotations

import time
from typing import Any

from fastapi import APIRouter, Response
from sqlalchemy import text

from schemas.api import Health
from server.api.contract import problems
from server.api.deps import Caller, State
from server.buildings.registry import failing_buildings
from server.errors import ForbiddenError
from server.state import AppState
from server.storage import free_bytes

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def get_health(state: State) -> Health:
    with state.engine.connect() as connection:
        connection.execute(text("SELECT 1"))
    failing = failing_buildings(state.tracking, time.time())
    free = free_bytes(state.settings.data_dir)
    low_disk = free < state.settings.min_free_disk_gb * 1e9
    return Health(
        status="degraded" if failing or low_disk else "ok",
        database=state.engine.dialect.name,
        buildings_loaded=len(state.tracking.handles),
        failing_buildings=failing,
        disk_free_bytes=free,
        low_disk=low_disk,
    )


_METRICS_MEDIA_TYPE = "text/plain; version=0.0.4"
_METRICS_OK: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "Prometheus metrics.",
        "content": {_METRICS_MEDIA_TYPE: {"schema": {"type": "string"}}},
    }
}


def _render(state: AppState) -> Response:
    body = state.metrics.render(state.tracking, state.broadcaster, state.storage.storage())
    return Response(body, media_type=_METRICS_MEDIA_TYPE)


def metrics_router(need_key: bool) -> APIRouter:
    """``GET /metrics``: open, or with ``CROWDSLAM_METRICS_NEED_KEY`` only for a site-wide operator key (the
    figures name every building). Its spec says which: the route is the one this server runs."""
    metrics_router = APIRouter(tags=["health"])
    if not need_key:

        @metrics_router.get("/metrics", response_class=Response, responses=_METRICS_OK)
        async def get_metrics(state: State) -> Response:
            """Prometheus metrics."""
            return _render(state)

        return metrics_router

    @metrics_router.get(
        "/metrics",
        response_class=Response,
        responses={**_METRICS_OK, **problems((403, "Only a site-wide operator key reads the metrics."))},
    )
    async def get_metrics_with_key(state: State, caller: Caller) -> Response:
        """Prometheus metrics, for a site-wide operator key (the figures name every building)."""
        caller.require_operator()
        if caller.building_id is not None:
            raise ForbiddenError("/metrics names every building: it needs a site-wide operator key")
        return _render(state)

    return metrics_router
