"""On a PostgreSQL whose autovacuum is off (as on the development machines), the server vacuums its own
tables by autovacuum's rule: the batch log's space is reused, where without a vacuum every batch would leave
its row behind for good."""

from __future__ import annotations

import random
import time

import pytest
from sqlalchemy import Engine, delete, insert, text

from server.store.db import make_engine
from server.store.migrate import upgrade
from server.store.models import BatchLogRow, BatchRow, BuildingRow
from server.store.vacuum import BackgroundVacuum, autovacuum_is_on, vacuum_in_background

pytestmark = pytest.mark.postgres

BODY = b"x" * 1200  # a batch's body, stored inline


def _churn(engine: Engine, first: int, n: int) -> None:
    """``n`` batches logged, then their log deleted (a snapshot covered them)."""
    with engine.begin() as conn:
        conn.execute(
            insert(BatchRow),
            [{"id": first + k, "building_id": "hq", "device_id": "p", "batch_id": f"b{first + k}", "seq": k,
              "n_bytes": 10, "applied": True, "tracker_call": k} for k in range(n)],
        )  # fmt: skip
        conn.execute(
            insert(BatchLogRow),
            [{"batch_row_id": first + k, "building_id": "hq", "tracker_call": k, "body": BODY}
             for k in range(n)],
        )  # fmt: skip
    with engine.begin() as conn:
        conn.execute(delete(BatchLogRow))


def _log_bytes(engine: Engine) -> int:
    with engine.connect() as conn:
        return int(conn.execute(text("SELECT pg_relation_size('batch_log')")).scalar_one())


def _wait_due(vacuum: BackgroundVacuum, table: str) -> list[str]:
    deadline = time.monotonic() + 10.0  # the statistics reach pg_stat_user_tables within a second or so
    while table not in (due := vacuum.due()) and time.monotonic() < deadline:
        time.sleep(0.2)
    return due


def test_the_server_vacuums_its_tables_when_autovacuum_is_off(postgres_url: str) -> None:
    engine = make_engine(postgres_url)
    upgrade(engine)
    with engine.begin() as conn:
        conn.execute(insert(BuildingRow).values(id="hq", name="HQ", rotation_rad=0.0))
    vacuum = BackgroundVacuum(engine, period_s=3600.0)  # stepped by hand
    try:
        _churn(engine, 0, 3000)
        grown = _log_bytes(engine)
        assert "batch_log" in _wait_due(vacuum, "batch_log")
        assert "batch_log" in vacuum.vacuum_due()
        for round_ in range(1, 4):  # the same churn again: the vacuumed space is reused
            _churn(engine, 3000 * round_, 3000)
            _wait_due(vacuum, "batch_log")
            vacuum.vacuum_due()
        assert _log_bytes(engine) <= 1.2 * grown
        assert vacuum.status.failures == 0
    finally:
        engine.dispose()
    assert not vacuum._thread.is_alive()  # stopped with the engine


def test_the_servers_vacuum_runs_only_where_autovacuum_does_not(postgres_url: str, sqlite_url: str) -> None:
    sqlite = make_engine(sqlite_url)
    assert vacuum_in_background(sqlite) is None
    sqlite.dispose()
    engine = make_engine(postgres_url)
    try:
        started = vacuum_in_background(engine, period_s=3600.0)
        assert (started is None) == autovacuum_is_on(engine)
    finally:
        engine.dispose()
    with pytest.raises(ValueError, match="PostgreSQL"):
        BackgroundVacuum(make_engine(sqlite_url))


def test_a_snapshot_rewritten_in_place_is_vacuumed_by_its_toast(postgres_url: str) -> None:
    """The tracker's snapshot is one row whose every rewrite leaves its megabytes as dead TOAST chunks: the
    table is due by its TOAST table's dead rows, long before its own one dead row a rewrite counts."""
    from server.store import repositories as repo
    from server.store.db import make_session_factory

    engine = make_engine(postgres_url)
    upgrade(engine)
    with engine.begin() as conn:
        conn.execute(insert(BuildingRow).values(id="hq", name="HQ", rotation_rad=0.0))
    sessions = make_session_factory(engine)
    vacuum = BackgroundVacuum(engine, period_s=3600.0)
    try:
        for k in range(3):  # three rewrites of an incompressible 400 kB state
            with sessions.begin() as session:
                repo.save_tracker_snapshot(session, "hq", 14, k, random.Random(k).randbytes(400_000))
        assert "tracker_snapshots" in _wait_due(vacuum, "tracker_snapshots")
        assert "tracker_snapshots" in vacuum.vacuum_due()
    finally:
        engine.dispose()
