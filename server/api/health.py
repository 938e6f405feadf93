"""Liveness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response
from sqlalchemy import text

from schemas.api import Health
from server.api.deps import State

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz(state: State) -> Health:
    with state.engine.connect() as connection:
        connection.execute(text("SELECT 1"))
    return Health(database=state.engine.dialect.name, buildings_loaded=len(state.tracking.workers))


@router.get("/metrics", response_class=Response)
def metrics(state: State) -> Response:
    body = state.metrics.render(state.tracking, state.broadcaster)
    return Response(body, media_type="text/plain; version=0.0.4")
