"""``crowdslam serve``: the HTTP and WebSocket server (uvicorn), or in a cluster a front or a worker."""

from __future__ import annotations

import argparse

from server.cli import tls_options
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
    tls_options.add_arguments(parser)


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

    tls = tls_options.tls_files(args, settings, "serve")
    if tls is not None:
        where = tls_options.public_base(args.host, args.port, tls)
        print(
            f"crowdslam serve: HTTPS ({tls.cert}); phones open {where}/phone/ by a dashboard's phone link",
            flush=True,
        )
    import uvicorn

    from server.app import create_app
    from server.cli.kernel_progress import KernelProgress

    try:
        app = create_app(settings, tune_gc=True, warming=KernelProgress("crowdslam serve"))
    except ValueError as exc:  # a setting only the app can read (CROWDSLAM_WEBHOOK_ALLOWED_HOSTS)
        raise SystemExit(f"crowdslam serve: {exc}") from None
    uvicorn.run(
        app,
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        ws="websockets-sansio",
        ws_per_message_deflate=settings.ws_compression,
        ws_max_size=settings.max_ws_frame_bytes,
        ssl_certfile=None if tls is None else str(tls.cert),
        ssl_keyfile=None if tls is None else str(tls.key),
    )
    return 0
