"""Shared fixtures. Databases are always built by running the migrations, never by create_all."""

from __future__ import annotations

import json
import os
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import Engine, text

from server.datasets.fetch import dataset_dir
from server.slam.numba_cache import configure_numba_cache
from server.store.db import make_engine
from server.store.migrate import upgrade

configure_numba_cache()  # before any test module imports numba: caches keyed by the kernel sources
# Buildings run in threads unless a test asks for processes (the server's default on more than one core): many
# tests look into a building's tracker, which a process of its own would hide. The tests of the default itself
# (the demo, the dashboard) take this variable out of their servers' environment.
os.environ.setdefault("CROWDSLAM_BUILDING_PROCESSES", "false")

ROOT = Path(__file__).resolve().parents[1]
TESTBED = ROOT / "server" / "data" / "paper-testbed.json"
"""The paper's testbed as the package ships it (``crowdslam demo`` and ``evaluate --scenario`` read it)."""
SAMPLE_WALKS = ROOT / "tests" / "data" / "msindoor20"
SAMPLE_FLOOR = SAMPLE_WALKS / "site1" / "F1"
"""Eight real walks of one floor with its plan, shipped with the tests (the data set's MIT licence)."""

WITHOUT_SHARED = "CROWDSLAM_TESTS_WITHOUT_SHARED"
"""Set, the tests ignore ``../shared`` as a clone without it would: CI runs the walks' tests so once more."""


def public_walks() -> Path | None:
    """The whole public data set: ``../shared``'s copy (unless ``CROWDSLAM_TESTS_WITHOUT_SHARED``), else the
    one ``crowdslam datasets fetch msindoor20`` put in the data directory (``CROWDSLAM_DATA_DIR``, by default
    ``crowdslam-data`` in the repository); None where neither is."""
    shared = ROOT.parent / "shared" / "data" / "msindoor20"
    if not os.environ.get(WITHOUT_SHARED) and shared.is_dir():
        return shared
    fetched = dataset_dir(ROOT / os.environ.get("CROWDSLAM_DATA_DIR", "crowdslam-data"))
    return fetched if fetched.is_dir() else None


def whole_floor(name: str) -> Path:
    """A whole floor of the public walks (``site1/F1``), or the test is skipped saying how to get it."""
    root = public_walks()
    floor = None if root is None else root / name
    if floor is None or not (floor / "path_data_files").is_dir():
        pytest.skip(
            f"needs the whole floor {name} of the public walks: run `crowdslam datasets fetch msindoor20 "
            f"--floors {name}` (or have ../shared beside the repository)"
        )
    return floor


def write_testbed(path: Path, users: int, walk_length_m: float | None = None) -> Path:
    """The paper testbed with fewer users (and shorter walks), written to ``path`` for a command to read."""
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = users
    if walk_length_m is not None:
        raw["users"]["walk_length_m"] = walk_length_m
    path.write_text(json.dumps(raw))
    return path


POSTGRES_ADMIN_URL = os.environ.get(
    "CROWDSLAM_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"
)


def _postgres_unavailable(reason: str) -> None:
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"PostgreSQL is required under CI=true but is unreachable: {reason}")
    pytest.skip(f"PostgreSQL unreachable: {reason}")


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """A fresh, empty PostgreSQL database for one test, dropped afterwards."""
    admin = make_engine(POSTGRES_ADMIN_URL, isolation_level="AUTOCOMMIT")
    name = f"crowdslam_t_{uuid.uuid4().hex[:12]}"
    try:
        with admin.connect() as connection:
            connection.execute(text(f'CREATE DATABASE "{name}"'))
    except Exception as error:  # any connection failure means "unreachable" here
        admin.dispose()
        _postgres_unavailable(str(error).splitlines()[0])
    url = admin.url.set(database=name).render_as_string(hide_password=False)
    try:
        yield url
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture
def sqlite_url(tmp_path: Path) -> str:
    return f"sqlite:///{tmp_path / 'crowdslam.sqlite3'}"


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def database_url(request: pytest.FixtureRequest) -> str:
    """An empty database URL, once for SQLite and once for the local PostgreSQL."""
    fixture = "sqlite_url" if request.param == "sqlite" else "postgres_url"
    return str(request.getfixturevalue(fixture))


@pytest.fixture
def migrated_engine(database_url: str) -> Iterator[Engine]:
    engine = make_engine(database_url)
    upgrade(engine)
    try:
        yield engine
    finally:
        engine.dispose()
