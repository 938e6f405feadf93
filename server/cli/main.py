"""Entry point of the ``crowdslam`` console script.

Subcommand modules are imported only when their command runs, so ``crowdslam --help`` stays fast
(no numpy, numba, SQLAlchemy or FastAPI import).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from server.cli import user_errors
from server.cli.user_errors import OneLineParser

# name -> (module implementing ``add_arguments(parser)`` and ``run(args) -> int``, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "schema": ("server.cli.schema_cmd", "write the JSON Schema of every public model, or print an example"),
    "migrate": ("server.cli.migrate_cmd", "upgrade the database (SQLite by default) to the latest schema"),
    "keys": ("server.cli.keys_cmd", "mint API keys (the first operator key comes from here)"),
    "serve": ("server.cli.serve_cmd", "run the HTTP and WebSocket server"),
    "simulate": ("server.cli.simulate_cmd", "drive a simulated crowd of phones against a running server"),
    "demo": ("server.cli.demo_cmd", "the server on SQLite with a simulated crowd posting over HTTP"),
    "replay": (
        "server.cli.replay_cmd",
        "feed an MCAP recording through the ingestion path (offline or to a server)",
    ),
    "import-msindoor": (
        "server.cli.import_msindoor_cmd",
        "turn Indoor Location 2.0 walks into an MCAP recording",
    ),
    "evaluate": (
        "server.cli.evaluate_cmd",
        "run the simulated testbed (or a sweep), or replay real walks as a crowd; metrics as JSON",
    ),
    "signalslam": (
        "server.cli.signalslam_cmd",
        "SignalSLAM on a floor of real walks: PDR, recalibrated PDR, GraphSLAM, SignalSLAM, fingerprints",
    ),
    "datasets": (
        "server.cli.datasets_cmd",
        "fetch the public walks the project measures on (Indoor Location Competition 2.0, MIT)",
    ),
    "calibrate": (
        "server.cli.calibrate_cmd",
        "fit the encounter models on a floor of real walks; precision and recall of each WiFi feature",
    ),
}


def build_parser() -> OneLineParser:
    parser = OneLineParser(
        prog="crowdslam",
        description="Indoor localization server without a site survey (DynamicSLAM + SignalSLAM).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=OneLineParser)
    for name, (module_name, help_text) in COMMANDS.items():
        command_parser = sub.add_parser(name, help=help_text, description=help_text)
        command_parser.set_defaults(_module=module_name)
        # Arguments are declared by the command module, loaded only for the command being parsed.
        if name in _requested_commands():
            importlib.import_module(module_name).add_arguments(command_parser)
    return parser


def _requested_commands() -> set[str]:
    return {arg for arg in sys.argv[1:] if arg in COMMANDS}


def main(argv: Sequence[str] | None = None) -> int:
    if argv is not None:
        sys.argv = [sys.argv[0], *argv]
    parser = build_parser()
    if len(sys.argv) == 1:  # no command: what there is to run
        parser.print_help()
        return 0
    args = parser.parse_args()
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from server.slam.numba_cache import configure_numba_cache

    try:
        configure_numba_cache()
        return int(importlib.import_module(args._module).run(args))
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into `head` and closed early
        sys.stderr.close()
        return 0
    except Exception as exc:
        if _interrupted(exc):
            return 130
        line = user_errors.message(exc)
        if line is None:
            raise  # a bug: the traceback is what a report needs
        sys.stderr.write(f"crowdslam {args.command}: {line}\n")
        return user_errors.EXIT_USER_ERROR


def _interrupted(exc: BaseException) -> bool:
    """Whether Ctrl-C caused ``exc``: an extension module interrupted while it initialises raises an
    ``ImportError`` whose cause is the ``KeyboardInterrupt``."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, KeyboardInterrupt):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


if __name__ == "__main__":
    raise SystemExit(main())
