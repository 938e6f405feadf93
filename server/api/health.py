"""Liveness and Prometheus metrics."""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, Header, Response
from sqlalchemy import text

from schemas.api import FailingBuilding, Health
from server.api.deps import State, principal
from server.errors import ForbiddenError

router = APIRouter(tags=["health"])


DEGRADED_S = 300.0
"""A building that refused a batch this recently makes the server ``degraded``."""


@router.get("/healthz", response_model=Health)
def healthz(state: State) -> Health:
    with state.engine.connect() as connection:
        connection.execute(text("SELECT 1"))
    workers = state.tracking.workers
    now = time.time()
    failing = [
        FailingBuilding(
            building_id=building_id,
            failed_batches=counters.failed_batches,
            last_failure_ms=int(counters.last_failure_unix_s * 1000),
        )
        for building_id, worker in sorted(workers.items())
        if (counters := worker.counters).failed_batches and now - counters.last_failure_unix_s < DEGRADED_S
    ]
    return Health(
        status="degraded" if failing else "ok",
        database=state.engine.dialect.name,
        buildings_loaded=len(workers),
        failing_buildings=failing,
    )


@router.get("/metrics", response_class=Response)
async def metrics(state: State, authorization: Annotated[str | None, Header()] = None) -> Response:
    """Prometheus metrics; with ``CROWDSLAM_METRICS_NEED_KEY`` only for a site-wide operator key (the
    figures name every building)."""
    if state.settings.metrics_need_key:
        caller = await principal(state, authorization)
        caller.require_operator()
        if caller.building_id is not None:
            raise ForbiddenError("/metrics names every building: it needs a site-wide operator key")
    body = state.metrics.render(state.tracking, state.broadcaster)
    return Response(body, media_type="text/plain; version=0.0.4")
