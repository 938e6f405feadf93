"""A live server on a fresh SQLite database holding building ``hq``, a site-wide operator key and the device
key of ``phone-1``: what an integrator outside the project would call."""

from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from schemas.api import KeyScope
from server.app import create_app
from server.auth import mint_key
from server.cli.background_server import free_port, running_server
from server.settings import Settings
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade
from server.store.models import BuildingRow


@dataclass(frozen=True)
class Served:
    base: str
    keys: dict[str, str]
    """``operator`` (site-wide) and ``device`` (``phone-1`` of ``hq``)."""
    spec: dict[str, Any]
    """The spec as the app serves it (a copy: schemathesis rewrites the dict it is given)."""


def seeded_database(path: Path) -> dict[str, str]:
    """Building ``hq`` and the two keys, in a migrated SQLite database at ``path``."""
    engine = make_engine(f"sqlite:///{path}")
    upgrade(engine)
    with make_session_factory(engine).begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
        session.flush()
        keys = {
            "operator": mint_key(session, KeyScope.OPERATOR)[0],
            "device": mint_key(session, KeyScope.DEVICE, "hq", "phone-1")[0],
        }
    engine.dispose()
    return keys


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    database = tmp_path_factory.mktemp("served") / "db.sqlite3"
    keys = seeded_database(database)
    app = create_app(Settings(data_dir=database.parent, database_url=f"sqlite:///{database}", record=False))
    with running_server(app, "127.0.0.1", free_port()) as base:
        yield Served(base, keys, copy.deepcopy(app.openapi()))
