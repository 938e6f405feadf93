"""The application factory and its typed lifespan: database, tracking, broadcaster, warmed kernels."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import logging
import multiprocessing
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker
from starlette.exceptions import HTTPException as StarletteHTTPException

from schemas.errors import Problem
from server.auth import KeyCache
from server.broadcast import Broadcaster
from server.errors import InvalidInputError, ProblemError, problem_response_parts
from server.ingestion import TrackingService
from server.kernel_warmup import warm_kernels
from server.metrics import Metrics
from server.recording import BuildingRecorder
from server.session_types import Retention
from server.settings import Settings
from server.signal_maps import SignalMapService
from server.store.db import make_engine, make_session_factory
from server.store.migrate import current_revision, head_revision
from server.store.wal_checkpoints import checkpoint_in_background
from server.tracking import BuildingSession
from slam_core.crowd_fingerprints import FingerprintParams
from slam_core.encounter_detection import DetectionParams
from slam_core.encounters import Calibration
from slam_core.params import BuildingAnchorParams, FilterParams, extended_confusion
from slam_core.tracker import TrackerParams

logger = logging.getLogger(__name__)

if TYPE_CHECKING:
    from server.foxglove_live import FoxgloveLive

API_DESCRIPTION = """Indoor localization without a site survey. Phones post sensor batches
(`POST /v1/buildings/{id}/batches`), dashboards read positions (`GET .../positions`, `WS .../live`),
operators manage buildings, keys and anchor maps. Every error is an RFC 9457 problem body."""


@dataclass
class AppState:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    broadcaster: Broadcaster
    tracking: TrackingService
    metrics: Metrics
    started: float
    keys: KeyCache
    signal_maps: SignalMapService
    foxglove: FoxgloveLive | None = None


class DatabaseNotMigratedError(RuntimeError):
    pass


def load_calibration(path: Path | None) -> Calibration:
    if path is None:
        text = resources.files("server.data").joinpath("testbed_calibration.json").read_text()
    else:
        text = path.read_text()
    return Calibration.from_dict(json.loads(text))


def tracker_params(settings: Settings) -> TrackerParams:
    n_types = len(extended_confusion(10))
    return TrackerParams(
        filter=FilterParams(
            anchors=BuildingAnchorParams(confusion=extended_confusion(n_types)),
            use_human_anchors=settings.mode == "dynamicslam",
        ),
        detection=DetectionParams(wifi_model=settings.encounter_wifi_model),
        # other users' scans, like human anchors: off in semanticslam mode (building anchors only)
        fingerprints=FingerprintParams(enabled=settings.fingerprint_fixes and settings.mode == "dynamicslam"),
    )


def retention(settings: Settings) -> Retention:
    return Retention(
        position_history_days=settings.position_history_days or None,
        batch_ids_days=settings.batch_ids_days or None,
        user_idle_s=settings.user_idle_s or None,
    )


def prepare_building_process(settings: Settings) -> None:
    """A building's own process (``server.building_process``): kernels warm and the GC tuned before its
    first batch, as the front's lifespan does for buildings in its own process."""
    _warm_kernels_for(settings)
    tune_gc_for_serving()


def compile_kernels_in_child(settings: Settings) -> None:
    """For buildings in processes of their own: compile every kernel once into numba's on-disk cache, in a
    short-lived child, before the server takes requests. Each building's process warms its kernels when
    it starts, at its building's first request; on a cold cache that is a compile of ~30 s (2-core machine,
    ~1.6 s from the cache), which the building's first batches waited for (a fresh install's first
    2,000-phone load run backed up by 32 s) and which buildings starting together would each repeat. A
    child rather than the front itself, so that the front does not keep compiled code it never runs."""
    started = time.perf_counter()
    process = multiprocessing.get_context("spawn").Process(
        target=_warm_kernels_for, args=(settings,), name="crowdslam-compile-kernels"
    )
    process.start()
    process.join()
    if process.exitcode != 0:
        raise RuntimeError(f"compiling the kernels failed in their process (exit code {process.exitcode})")
    logger.info("kernels compiled into the cache in %.1f s", time.perf_counter() - started)


def _warm_kernels_for(settings: Settings) -> None:
    warm_kernels(tracker_params(settings), load_calibration(settings.encounter_calibration))


def building_session(settings: Settings, building_id: str, engine: Engine | None = None) -> BuildingSession:
    """A building's session as the settings describe it, on its own database engine (a building's
    process; ``engine``: that engine, made by the caller, who disposes of it), its write-ahead log
    checkpointed beside the batch path; raises NotFoundError for an unknown building."""
    engine = engine or make_engine(settings.resolved_database_url)
    checkpoint_in_background(engine, settings.sqlite_checkpoint_period_s)  # stops when the process does
    sessions = make_session_factory(engine)
    recorder = BuildingRecorder(settings.recordings_dir, building_id) if settings.record else None
    return BuildingSession(
        building_id,
        sessions,
        tracker_params(settings),
        load_calibration(settings.encounter_calibration),
        settings.seed,
        recorder,
        settings.snapshot_period_s,
        retention(settings),
    )


def tune_gc_for_serving() -> None:
    """For a process that is the server: everything built so far (compiled kernels, SQLAlchemy and pydantic
    machinery) lives as long as the server, so it is kept out of the cyclic collector, whose full passes
    over it paused the event loop for up to 0.2 s under load; and young collections run every 10,000
    allocations instead of 700, full ones ten times more rarely (the batch path makes few cycles). At 400
    load-bench phones p99 went from 250 ms to 45-100 ms."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(10_000, 10, 100)


def create_app(settings: Settings, tune_gc: bool = False) -> FastAPI:
    """The app; ``tune_gc`` when it is the process's only job (``crowdslam serve``, ``demo``): the garbage
    collector is then tuned for its latency at the end of start-up (``tune_gc_for_serving``), process-wide."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        url = settings.resolved_database_url
        engine = make_engine(url)
        checkpoint_in_background(engine, settings.sqlite_checkpoint_period_s)  # stops with engine.dispose()
        current, head = current_revision(engine), head_revision(engine)
        if current != head:
            engine.dispose()
            raise DatabaseNotMigratedError(
                f"the database is at revision {current!r}, the server needs {head!r}: run `crowdslam migrate`"
            )
        sessions = make_session_factory(engine)
        broadcaster = Broadcaster()
        foxglove_live = None
        if settings.foxglove_port is not None:
            from server.foxglove_live import FoxgloveLive  # only when asked: the SDK starts a server

            foxglove_live = FoxgloveLive(settings.foxglove_host, settings.foxglove_port)
            broadcaster.add_sink(foxglove_live.publish)
        params = tracker_params(settings)
        calibration = load_calibration(settings.encounter_calibration)
        try:
            if settings.building_processes:
                await asyncio.to_thread(compile_kernels_in_child, settings)
            else:
                warm_kernels(params, calibration)
        except BaseException:
            engine.dispose()  # and its checkpoint thread: a server that cannot compile does not start
            raise
        recordings = settings.recordings_dir if settings.record else None
        tracking = TrackingService(
            sessions,
            broadcaster,
            params,
            calibration,
            settings.seed,
            recordings,
            settings.snapshot_period_s,
            retention(settings),
            settings if settings.building_processes else None,
        )
        app.state.crowdslam = AppState(
            settings,
            engine,
            sessions,
            broadcaster,
            tracking,
            Metrics(),
            time.time(),
            KeyCache(settings.key_cache_s),
            SignalMapService(
                settings.data_dir / "signal_maps", recordings, tuple(settings.signal_map_modalities)
            ),
            foxglove_live,
        )
        if tune_gc:
            tune_gc_for_serving()
        revalidation = asyncio.get_running_loop().create_task(_revalidate_keys_forever(app.state.crowdslam))
        try:
            yield
        finally:
            revalidation.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await revalidation
            app.state.crowdslam.signal_maps.close()
            await tracking.close()
            if foxglove_live is not None:
                foxglove_live.close()
            engine.dispose()

    app = FastAPI(
        title="crowdslam",
        version="1.0.0",
        description=API_DESCRIPTION,
        lifespan=lifespan,
        responses={
            401: {"model": Problem, "description": "Missing or unknown key"},
            403: {"model": Problem, "description": "The key's scope does not allow this"},
        },
        telemetry=None if settings.fastapi_telemetry else {"tracing": False, "metrics": False, "logs": False},
    )
    _install_error_handlers(app)
    from server.api import anchors, batches, buildings, health, live, positions, signal_maps

    for module in (health, buildings, batches, positions, anchors, live, signal_maps):
        app.include_router(module.router)
    app.add_middleware(batches.BatchFastPath)
    _document_raw_bodies(app)
    return app


async def _revalidate_keys_forever(state: AppState) -> None:
    """Every half key-cache lifetime, re-check every cached key in one query (``KeyCache.revalidate``); a
    failed round is logged and the entries simply age meanwhile."""
    from server.deps import revalidate_keys  # deps imports this module

    period = state.settings.key_cache_s / 2
    if period <= 0:
        return
    while True:
        await asyncio.sleep(period)
        try:
            await revalidate_keys(state)
        except Exception:
            logger.exception("revalidating the key cache failed; cached keys will expire")


def _document_raw_bodies(app: FastAPI) -> None:
    """The batch endpoint reads its body itself (size before parsing); publish the SensorBatch schema."""
    from fastapi.openapi.utils import get_openapi

    from schemas.sensors import SensorBatch

    def openapi() -> dict[str, object]:
        if app.openapi_schema is None:
            spec = get_openapi(
                title=app.title, version=app.version, description=app.description, routes=app.routes
            )
            schema = SensorBatch.model_json_schema(ref_template="#/components/schemas/{model}")
            components = spec.setdefault("components", {}).setdefault("schemas", {})
            components.update(schema.pop("$defs", {}))
            components["SensorBatch"] = schema
            app.openapi_schema = spec
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def _install_error_handlers(app: FastAPI) -> None:
    def problem_response(problem: Problem) -> Response:
        status, body, headers = problem_response_parts(problem)
        return Response(body, status_code=status, headers=headers)

    @app.exception_handler(ProblemError)
    async def _problem(_: Request, exc: ProblemError) -> Response:
        return problem_response(exc.to_problem())

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> Response:
        from server.errors import field_problem

        problems = [field_problem(e) for e in exc.errors()]
        error = InvalidInputError(
            f"{len(problems)} field(s) invalid: " + "; ".join(f"{p.loc}: {p.msg}" for p in problems[:5]),
            problems,
        )
        return problem_response(error.to_problem())

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> Response:
        title = {404: "Not found", 405: "Method not allowed"}.get(exc.status_code, "HTTP error")
        return problem_response(Problem(title=title, status=exc.status_code, detail=str(exc.detail)))

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception) -> Response:
        return problem_response(
            Problem(
                title="Internal server error",
                status=500,
                detail=f"{type(exc).__name__}: the error was logged",
            )
        )
