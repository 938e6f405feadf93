"""The application factory and its typed lifespan: database, tracking, broadcaster, warmed kernels."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from sqlalchemy.orm import Session, sessionmaker
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import Receive, Scope, Send

from schemas.errors import Problem
from server import __version__
from server.api import (
    anchors,
    batches,
    buildings,
    current_key,
    health,
    live,
    positions,
    signal_maps,
    users,
    webhooks,
    zones,
)
from server.api.contract import allowed_methods, install_openapi, operation_id
from server.api.deps import revalidate_keys
from server.api.limits import BATCHES_PATH, BodyLimit
from server.auth import KeyCache
from server.buildings.calls import LoadRadioMap
from server.buildings.registry import Buildings, TrackingService
from server.dashboard.pages import install_pages
from server.errors import (
    InvalidInputError,
    ProblemError,
    UnexpectedError,
    field_problem,
    problem_response_parts,
)
from server.gc_tuning import tune_gc_for_serving
from server.live.broadcast import Broadcaster
from server.metrics import Metrics
from server.phone.pages import install_phone_page
from server.rate_limit import RateLimiter, retry_after_header
from server.settings import Settings
from server.signal_maps.jobs import SignalMapService
from server.slam.config import load_calibration, tracker_params
from server.slam.warmup import Progress, compile_kernels_in_child, warm_kernels
from server.state import AppState
from server.storage import StorageWatch
from server.store.db import make_engine, make_session_factory
from server.store.migrate import current_revision, head_revision
from server.store.vacuum import vacuum_in_background
from server.store.wal_checkpoints import checkpoint_in_background
from server.webhooks.addresses import AllowedHosts
from server.webhooks.dispatcher import DispatchConfig, Dispatcher

logger = logging.getLogger(__name__)

API_DESCRIPTION = """Indoor localization without a site survey. Phones post sensor batches
(`POST /v1/buildings/{id}/batches`), dashboards read positions (`GET .../positions`, `WS .../live`),
operators manage buildings, keys and anchor maps. Every error is an RFC 9457 problem body."""


class CrowdslamApp(FastAPI):
    """The FastAPI app, but for ``POST /v1/buildings/{id}/batches``, which it hands straight to
    ``server.api.batches.serve_batch`` (unless ``batch_fast_path`` is off): the middleware chain in between
    (errors, telemetry, the body limits, which that path applies itself) cost a tenth of the front's CPU a
    batch."""

    batch_fast_path = True

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if self.batch_fast_path and scope["type"] == "http" and scope["method"] == "POST":
            match = BATCHES_PATH.fullmatch(scope["path"])
            if match is not None:
                await batches.serve_batch(self.state.crowdslam, match.group(1), scope, receive, send)
                return
        await super().__call__(scope, receive, send)


class DatabaseNotMigratedError(RuntimeError):
    pass


class ClusterMisconfiguredError(RuntimeError):
    pass


def create_app(settings: Settings, tune_gc: bool = False, warming: Progress | None = None) -> CrowdslamApp:
    """The app; ``tune_gc`` when it is the process's only job (``crowdslam serve``, ``demo``): the garbage
    collector is then tuned for its latency at the end of start-up (``tune_gc_for_serving``), process-wide.
    ``warming`` hears how the start-up's compile of the filter's kernels goes (a minute on a cold cache)."""

    allowed_hosts = AllowedHosts.parse(settings.webhook_allowed_hosts)  # a typo stops the start, named

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        url = settings.resolved_database_url
        engine = make_engine(url)
        if not settings.resolved_building_processes:
            # the buildings write through this engine; in processes of their own, each checkpoints the log
            # its batches fill, and a second thread here copied the same pages again (4 % of the front's CPU)
            checkpoint_in_background(engine, settings.sqlite_checkpoint_period_s)  # stops with dispose()
        current, head = current_revision(engine), head_revision(engine)
        if current != head:
            engine.dispose()
            raise DatabaseNotMigratedError(
                f"the database is at revision {current!r}, the server needs {head!r}: run `crowdslam migrate`"
            )
        vacuum_in_background(engine)  # PostgreSQL without autovacuum; stops with engine.dispose()
        sessions = make_session_factory(engine)
        broadcaster = Broadcaster()
        foxglove_live = None
        if settings.foxglove_port is not None:
            from server.live.foxglove import FoxgloveLive  # only when asked: the SDK starts a server

            foxglove_live = FoxgloveLive(settings.foxglove_host, settings.foxglove_port)
            broadcaster.add_sink(foxglove_live.publish)
        recordings = settings.recordings_dir if settings.record else None
        try:
            tracking, disconnect = await _buildings(settings, sessions, broadcaster, warming)
        except BaseException:
            engine.dispose()  # and its checkpoint thread: a server that cannot track does not start
            raise
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
            StorageWatch(settings.data_dir, engine),
            foxglove_live,
            RateLimiter(settings.device_rate_per_s, settings.device_burst),
        )
        if tune_gc:
            tune_gc_for_serving()
        loop = asyncio.get_running_loop()
        revalidation = loop.create_task(_revalidate_keys_forever(app.state.crowdslam))
        # every serving process sends the webhook deliveries its buildings' transactions queued (claimed one
        # by one: a cluster's fronts share them)
        dispatch = loop.create_task(
            Dispatcher(
                sessions,
                DispatchConfig(
                    allowed_hosts,
                    settings.webhook_max_attempts,
                    settings.webhook_retry_s,
                    settings.webhook_timeout_s,
                ),
            ).run()
        )
        loading: set[asyncio.Task[None]] = set()  # held until done: the loop keeps only weak references

        def built(building_id: str) -> None:
            task = loop.create_task(_load_radio_map(tracking, app.state.crowdslam.signal_maps, building_id))
            loading.add(task)
            task.add_done_callback(loading.discard)

        app.state.crowdslam.signal_maps.on_built = lambda b: loop.call_soon_threadsafe(built, b)
        try:
            yield
        finally:
            revalidation.cancel()
            dispatch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await revalidation
            with contextlib.suppress(asyncio.CancelledError):
                await dispatch
            app.state.crowdslam.signal_maps.close()
            await tracking.close()
            await disconnect()
            if foxglove_live is not None:
                foxglove_live.close()
            engine.dispose()

    app = CrowdslamApp(
        title="crowdslam",
        version=__version__,
        description=API_DESCRIPTION,
        lifespan=lifespan,
        generate_unique_id_function=operation_id,
        telemetry=None if settings.fastapi_telemetry else {"tracing": False, "metrics": False, "logs": False},
        docs_url=None,  # served by install_pages from local assets
        redoc_url=None,
    )
    app.state.settings = settings  # what serves the app reads (the WebSocket frame bound)
    _install_error_handlers(app)
    for module in (
        health,
        current_key,
        buildings,
        batches,
        positions,
        users,
        anchors,
        zones,
        webhooks,
        live,
        signal_maps,
    ):
        app.include_router(module.router)
    app.include_router(health.metrics_router(settings.metrics_need_key))
    install_pages(app)
    install_phone_page(app)
    app.batch_fast_path = not settings.fastapi_telemetry  # telemetry's spans wrap every request
    app.add_middleware(BodyLimit, limit=settings.max_request_bytes, plan_limit=settings.max_plan_bytes)
    install_openapi(app)
    return app


async def _buildings(
    settings: Settings,
    sessions: sessionmaker[Session],
    broadcaster: Broadcaster,
    warming: Progress | None,
) -> tuple[Buildings, Callable[[], Awaitable[None]]]:
    """The buildings as this process reaches them, and what disconnects it from them once they are closed:
    tracked here (the embedded role: kernels compiled first), or by the cluster's workers (a front)."""
    if settings.role == "front":
        from server.cluster.batch_stream import BatchStream  # only a front needs NATS
        from server.cluster.connection import connect
        from server.cluster.front import ClusterBuildings

        problem = settings.cluster_problem()
        if problem is not None:
            raise ClusterMisconfiguredError(problem)
        assert settings.nats_url is not None
        connection = await connect(settings.nats_url, "crowdslam-front")
        try:
            front = await ClusterBuildings.start(
                connection,
                BatchStream(),
                sessions,
                broadcaster,
                settings.receipt_timeout_s,
                settings.stream_retention_s,
            )
        except BaseException:
            await connection.close()
            raise

        async def drain() -> None:
            with contextlib.suppress(Exception):
                await connection.drain()

        return front, drain
    if settings.role != "all":
        raise ClusterMisconfiguredError(
            f"CROWDSLAM_ROLE={settings.role} runs without HTTP: start it with `crowdslam serve --role worker`"
        )
    if settings.resolved_building_processes:
        await compile_kernels_in_child(settings, warming)
    else:
        warm_kernels(tracker_params(settings), load_calibration(settings.encounter_calibration), warming)
    tracking = TrackingService(
        sessions, broadcaster, settings, in_processes=settings.resolved_building_processes
    )

    async def nothing() -> None:
        return None

    return tracking, nothing


async def _load_radio_map(tracking: Buildings, signal_maps: SignalMapService, building_id: str) -> None:
    """A finished build's radio map joins its building's fingerprints, in order with its batches; the build's
    record then says how many of its scans joined."""
    try:
        building = await tracking.handle(building_id)
        loaded = await building.ask(LoadRadioMap())
        if loaded is not None:
            await asyncio.to_thread(signal_maps.loaded, building_id, *loaded)
    except Exception:
        logger.exception(
            "building %s: loading its new radio map failed; it loads at the next start", building_id
        )


async def _revalidate_keys_forever(state: AppState) -> None:
    """Every half key-cache lifetime, re-check every cached key in one query (``KeyCache.revalidate``); a
    failed round is logged and the entries simply age meanwhile."""
    period = state.settings.key_cache_s / 2
    if period <= 0:
        return
    while True:
        await asyncio.sleep(period)
        try:
            await revalidate_keys(state)
        except Exception:
            logger.exception("revalidating the key cache failed; cached keys will expire")


def _install_error_handlers(app: FastAPI) -> None:
    def problem_response(problem: Problem) -> Response:
        status, body, headers = problem_response_parts(problem)
        return Response(body, status_code=status, headers=headers)

    @app.exception_handler(ProblemError)
    async def _problem(_: Request, exc: ProblemError) -> Response:
        response = problem_response(exc.to_problem())
        if exc.retry_after_s is not None:
            response.headers["retry-after"] = retry_after_header(exc.retry_after_s)
        return response

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> Response:

        problems = [field_problem(e) for e in exc.errors()]
        error = InvalidInputError(
            f"{len(problems)} field(s) invalid: " + "; ".join(f"{p.loc}: {p.msg}" for p in problems[:5]),
            problems,
        )
        return problem_response(error.to_problem())

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        title = {400: "Malformed request body", 404: "Not found", 405: "Method not allowed"}.get(
            exc.status_code, "HTTP error"
        )
        response = problem_response(Problem(title=title, status=exc.status_code, detail=str(exc.detail)))
        response.headers.update(exc.headers or {})
        if exc.status_code == 405 and (methods := allowed_methods(app, request.url.path)):
            response.headers["allow"] = ", ".join(sorted(methods))
        return response

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception) -> Response:
        return problem_response(UnexpectedError().to_problem())
