"""``crowdslam serve``: the HTTP and WebSocket server (uvicorn)."""

from __future__ import annotations

import argparse

from server.cli.user_errors import port_number


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=port_number, default=8000)
    parser.add_argument(
        "--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"]
    )


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    import uvicorn

    from server.app import create_app
    from server.settings import get_settings

    settings = get_settings()
    app = create_app(settings, tune_gc=True)
    uvicorn.run(
        app,
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        ws="websockets-sansio",
        ws_per_message_deflate=settings.ws_compression,
    )
    return 0
