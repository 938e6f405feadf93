"""A user's mistake on the command line is one line on stderr and exit code 2, never a traceback: a missing
or unreadable file, a file that is not what the command reads, an unreachable server or database, a URL
that is not one, a port out of range."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

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


FETCH_HINT = (
    "`crowdslam datasets fetch msindoor20` puts the public floors in crowdslam-data/datasets/msindoor20"
)


def floor_folder(text: str) -> Path:
    """``--msindoor``: a floor of Indoor Location 2.0 walks (``floor_info.json`` and ``path_data_files/``), or
    a building whose subfolders are such floors (``B1``, ``F1``, ``F2``, ...)."""
    from server.datasets.msindoor import building_floors  # deferred: `crowdslam --help` loads no numpy

    path = Path(text)
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no such folder ({FETCH_HINT})")
    try:
        floors = building_floors(path)
    except ValueError:
        floors = []
    if not floors or not all((floor / "floor_info.json").is_file() for _, floor in floors):
        raise argparse.ArgumentTypeError(
            f"{text} is neither a floor of Indoor Location 2.0 walks (floor_info.json and path_data_files/) "
            f"nor a building of such floors named B1, F1, F2, ... ({FETCH_HINT})"
        )
    return path


def walks_folder(text: str) -> Path:
    """A floor, a building (its floors as subfolders ``B1``, ``F1``, ``F2``, ...), or a folder of Indoor
    Location 2.0 walks (``.txt``, each opening with its start time)."""
    from server.datasets.msindoor import building_floors  # deferred: `crowdslam --help` loads no numpy

    path = Path(text)
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no such folder ({FETCH_HINT})")
    if (path / "path_data_files").is_dir() or any(path.glob("*.txt")):
        folders = [path / "path_data_files" if (path / "path_data_files").is_dir() else path]
    else:
        try:
            folders = [floor / "path_data_files" for _, floor in building_floors(path)]
        except ValueError:
            folders = [path]
    walks = sorted(w for folder in folders for w in folder.glob("*.txt"))
    if not walks:
        raise argparse.ArgumentTypeError(f"{text}: no .txt walks in {folders[0]}")
    for walk in walks:
        with walk.open("rb") as source:
            if not source.read(64).startswith(b"#\tstartTime"):
                raise argparse.ArgumentTypeError(
                    f"{walk} is not an Indoor Location 2.0 walk (no startTime header)"
                )
    return path


def output_file(text: str) -> Path:
    """An output file (``--json``, ``--plot``), checked before a long run rather than after it: not a folder,
    in a folder that exists or can be made, and may be written."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder: give a file's name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise argparse.ArgumentTypeError(f"{text}: its folder cannot be made ({error.strerror})") from None
    if not os.access(path.parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise argparse.ArgumentTypeError(f"{text}: cannot be written here (permission denied)")
    return path


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
    # the modules below are checked only when loaded: a command that never loaded them cannot raise them
    msindoor = sys.modules.get("server.datasets.msindoor")
    if msindoor is not None and isinstance(exc, msindoor.TraceFormatError):
        return f"not readable as Indoor Location 2.0 walks: {exc}"
    httpx = sys.modules.get("httpx")
    if httpx is not None:
        if isinstance(exc, (httpx.UnsupportedProtocol, httpx.InvalidURL)):
            return f"not a usable URL ({exc}); give one like http://127.0.0.1:8000"
        if isinstance(exc, httpx.TransportError):
            return f"cannot reach the server: {exc}"
    pydantic = sys.modules.get("pydantic")
    if pydantic is not None and isinstance(exc, pydantic.ValidationError) and exc.title == "Settings":
        from server.settings import settings_problem

        return settings_problem(exc)
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
