"""A user's mistake on the command line is one line on stderr and exit code 2, never a traceback: a missing
or unreadable file, a file that is not what the command reads, an unreachable server or database, a URL
that is not one, a port out of range."""

from __future__ import annotations

import argparse
import json
import sys

EXIT_USER_ERROR = 2


class UserError(Exception):
    """Raised by a command for a mistake the user can mend; its message is the line printed."""


def port_number(text: str) -> int:
    """``--port``: 0 (any free port) to 65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port {port} is out of range (0-65535)")
    return port


def message(exc: BaseException) -> str | None:
    """The line to print for an exception that is the user's mistake, or None for a bug."""
    if isinstance(exc, UserError):
        return str(exc)
    if isinstance(exc, (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)):
        return f"{exc.filename}: {exc.strerror}"
    if isinstance(exc, json.JSONDecodeError):
        return f"not valid JSON: {exc}"
    if isinstance(exc, UnicodeDecodeError):
        return f"not a text file: {exc}"
    # the libraries below are checked only when loaded: a command that never loaded them cannot raise them
    httpx = sys.modules.get("httpx")
    if httpx is not None:
        if isinstance(exc, (httpx.UnsupportedProtocol, httpx.InvalidURL)):
            return f"not a usable URL ({exc}); give one like http://127.0.0.1:8000"
        if isinstance(exc, httpx.TransportError):
            return f"cannot reach the server: {exc}"
    sqlalchemy_exc = sys.modules.get("sqlalchemy.exc")
    if sqlalchemy_exc is not None:
        if isinstance(exc, sqlalchemy_exc.ArgumentError):
            return f"not a database URL: {exc}"
        if isinstance(exc, (sqlalchemy_exc.OperationalError, sqlalchemy_exc.InterfaceError)):
            cause = getattr(exc, "orig", None) or exc
            return "cannot reach the database: " + " ".join(str(cause).split())
    return None


class OneLineParser(argparse.ArgumentParser):
    """argparse's errors as one line on stderr (its usage stays in ``--help``)."""

    def error(self, text: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"{self.prog}: {text}\n")
        raise SystemExit(EXIT_USER_ERROR)
