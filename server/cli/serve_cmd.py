"""``crowdslam serve``: the HTTP and WebSocket server (uvicorn), or in a cluster a front or a worker."""

from __future__ import annotations

import argparse

from server.cli.user_errors import port_number


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=port_number, default=8000)
    parser.add_argument(
        "--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"]
    )
    parser.add_argument(
        "--role",
        choices=["all", "front", "worker"],
        default=None,
        help="all (default: CROWDSLAM_ROLE, else all): serve and track in this process. front: a stateless "
        "HTTP/WebSocket front of a cluster. worker: tracks the cluster's buildings (no HTTP).",
    )
    parser.add_argument(
        "--nats", default=None, metavar="URL", help="the cluster's NATS (default: CROWDSLAM_NATS_URL)"
    )


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from server.settings import get_settings, retired_variables

    for retired in retired_variables():
        raise SystemExit(f"crowdslam serve: {retired}")
    update: dict[str, object] = {}
    if args.role is not None:
        update["role"] = args.role
    if args.nats is not None:
        update["nats_url"] = args.nats
    settings = get_settings().model_copy(update=update)
    problem = settings.cluster_problem()
    if problem is not None:
        raise SystemExit(f"crowdslam serve: {problem}")
    if settings.role == "worker":
        import asyncio
        import logging

        from server.cluster.worker import serve

        logging.basicConfig(
            level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
        )
        asyncio.run(serve(settings))
        return 0

    if settings.http_server == "granian":
        try:
            import granian  # noqa: F401  (told before the app loads)
        except ImportError:
            needs = "needs granian: pip install 'crowdslam[granian]'"
            raise SystemExit(f"crowdslam serve: CROWDSLAM_HTTP_SERVER=granian {needs}") from None
    from server.app import create_app
    from server.cli.kernel_progress import KernelProgress

    app = create_app(settings, tune_gc=True, warming=KernelProgress("crowdslam serve"))
    if settings.http_server == "granian":
        return _serve_granian(app, args)
    import uvicorn

    uvicorn.run(
        app,
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        ws="websockets-sansio",
        ws_per_message_deflate=settings.ws_compression,
        ws_max_size=settings.max_ws_frame_bytes,
    )
    return 0


def _serve_granian(app: object, args: argparse.Namespace) -> int:
    """The app under granian's server embedded in this process: its HTTP/1.1 and WebSocket stack in Rust
    threads, the app on this process's event loop (so that building processes, the numba kernels and the
    metrics see one front process, as under uvicorn)."""
    import asyncio
    import signal

    import uvloop
    from granian.constants import Interfaces
    from granian.log import LogLevels
    from granian.server.embed import Server

    server = Server(
        app,
        address=args.host,
        port=args.port,
        interface=Interfaces.ASGI,
        log_level=LogLevels(args.log_level),
        backlog=2048,
    )

    async def serve() -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, server.stop)
        await server.serve()

    uvloop.run(serve())
    return 0
