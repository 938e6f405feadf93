"""A full disk refuses batches with 503 and Retry-After, keeps nothing of them and loses nothing acknowledged:
sent again once there is room, they apply as if the disk had never filled. SQLite's ``max_page_count`` stands
in for the disk."""

from __future__ import annotations

import pickle
from typing import Any

from sqlalchemy import Engine, event, func, select

from server.errors import DiskFullError, ProblemError
from server.store.db import is_disk_full, make_session_factory
from server.store.models import BatchRow
from tests.server.buildings.test_restart import (
    CROWD,
    _building,
    _estimates,
    _fresh_building,
    _groups,
    _pin_known,
)


def _rows(engine: Engine) -> int:
    with make_session_factory(engine)() as session:
        return int(session.execute(select(func.count()).select_from(BatchRow)).scalar_one())


def _limit_pages(engine: Engine, pages: int | None) -> Any:
    """Every new connection of ``engine`` may grow the database to ``pages`` pages (None: no limit)."""

    def limit(connection: Any, _: Any) -> None:
        connection.execute(f"PRAGMA max_page_count = {pages if pages is not None else 1073741823}")

    event.listen(engine, "connect", limit)
    engine.dispose()  # the pooled connections were opened without it
    return limit


def test_a_full_disk_refuses_a_group_whole_and_loses_nothing(sqlite_url: str) -> None:
    groups = _groups(CROWD, size=8)
    reference = _building(_fresh_building(sqlite_url.replace(".sqlite3", "-ref.sqlite3")))
    _pin_known(reference)
    for group in groups[:12]:
        reference.process(group)

    engine = _fresh_building(sqlite_url)
    building = _building(engine)
    _pin_known(building)
    for group in groups[:10]:
        building.process(group)
    before, rows = _estimates(building), _rows(engine)
    with engine.connect() as connection:
        pages = int(connection.exec_driver_sql("PRAGMA page_count").scalar_one())
    listener = _limit_pages(engine, pages)

    refused = building.process(groups[10])
    assert len(refused.receipts) == len(groups[10])
    assert all(isinstance(r, DiskFullError) for r in refused.receipts)
    error = refused.receipts[0]
    assert isinstance(error, ProblemError)
    assert (error.status, error.retry_after_s) == (503, 60.0)
    assert building.counters.disk_full_refusals == 1
    assert building.counters.failed_batches == 0  # refused to be sent again, not failed
    assert _rows(engine) == rows  # nothing of it kept
    assert _estimates(building) == before  # the building as it was

    event.remove(engine, "connect", listener)
    engine.dispose()
    for group in groups[10:12]:  # sent again, and the next
        result = building.process(group)
        assert all(r.status == "applied" for r in result.receipts)  # type: ignore[union-attr]
    assert _estimates(building) == _estimates(reference)
    building.close()
    reference.close()
    engine.dispose()


def test_what_counts_as_a_full_disk_and_the_answer_crosses_a_process_intact() -> None:
    import errno
    import sqlite3

    import psycopg.errors

    full = sqlite3.OperationalError("database or disk is full")
    full.sqlite_errorcode = 13  # type: ignore[attr-defined]
    locked = sqlite3.OperationalError("database is locked")
    locked.sqlite_errorcode = 5  # type: ignore[attr-defined]

    assert is_disk_full(full)
    assert is_disk_full(psycopg.errors.DiskFull("could not extend file: No space left on device"))
    assert is_disk_full(OSError(errno.ENOSPC, "No space left on device"))
    assert not is_disk_full(locked)
    assert not is_disk_full(OSError(errno.EACCES, "Permission denied"))
    again = pickle.loads(pickle.dumps(DiskFullError()))
    assert (again.status, again.retry_after_s, again.detail) == (503, 60.0, DiskFullError().detail)
