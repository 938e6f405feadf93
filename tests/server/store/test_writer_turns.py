"""Buildings sharing a SQLite file take turns at its write lock through a ``flock`` beside it: held for the
whole of a group's transaction, released after it, exclusive between two buildings of one process; nothing
for PostgreSQL or an in-memory database."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import threading
from pathlib import Path

import pytest

from server.store.db import make_engine
from server.store.writer_turns import WriterTurns, writer_turns
from tests.server.buildings.test_restart import CROWD, _building, _fresh_building


def _taken(path: Path) -> bool:
    """Whether another holder has the turn (a non-blocking try from a file of our own)."""
    with path.open("ab") as probe:
        try:
            fcntl.flock(probe.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(probe.fileno(), fcntl.LOCK_UN)
        return False


def test_a_turn_is_held_inside_and_free_after(tmp_path: Path) -> None:
    turns = WriterTurns(tmp_path / "db.sqlite3-writers.lock")
    assert not _taken(turns.path)
    with turns:
        assert _taken(turns.path)
        with pytest.raises(RuntimeError, match="already held"):  # a session never waits on itself
            turns.__enter__()
        assert _taken(turns.path)
    assert not _taken(turns.path)
    with pytest.raises(RuntimeError), turns:  # released on an error as well
        raise RuntimeError("the transaction failed")
    assert not _taken(turns.path)


def test_two_buildings_in_one_process_take_turns(tmp_path: Path) -> None:
    path = tmp_path / "db.sqlite3-writers.lock"
    first, second = WriterTurns(path), WriterTurns(path)
    entered = threading.Event()

    def take_second() -> None:
        with second:
            entered.set()

    with first:
        waiter = threading.Thread(target=take_second)
        waiter.start()
        assert not entered.wait(0.3)  # blocked while the first holds its turn
    assert entered.wait(10.0)  # and given the turn once it is released
    waiter.join()


def test_only_a_sqlite_file_has_turns(tmp_path: Path) -> None:
    file_engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    turns = writer_turns(file_engine)
    assert isinstance(turns, WriterTurns)
    assert turns.path == tmp_path / "db.sqlite3-writers.lock"
    assert isinstance(writer_turns(make_engine("sqlite://")), contextlib.nullcontext)
    postgres = make_engine("postgresql+psycopg://postgres@127.0.0.1:5432/test")
    assert isinstance(writer_turns(postgres), contextlib.nullcontext)
    for engine in (file_engine, postgres):
        engine.dispose()


def test_a_group_of_batches_waits_for_its_turn(tmp_path: Path) -> None:
    path = tmp_path / "db.sqlite3"
    engine = _fresh_building(f"sqlite:///{path}")
    building = _building(engine)
    other = WriterTurns(path.with_name(path.name + "-writers.lock"))  # another building's
    done = threading.Event()

    def process() -> None:
        building.process(CROWD[:4])
        done.set()

    with other:
        worker = threading.Thread(target=process)
        worker.start()
        assert not done.wait(0.5)  # the group waits while the other building writes
    assert done.wait(30.0)
    worker.join()
    assert building.counters.batches == 4
    building.close()
    engine.dispose()


def test_a_file_system_without_flock_falls_back_to_the_busy_handler(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    turns = WriterTurns(tmp_path / "db.sqlite3-writers.lock")
    calls = []

    def refuse(fd: int, operation: int) -> None:
        calls.append(operation)
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", refuse)
    with caplog.at_level(logging.WARNING, logger="server.store.writer_turns"):
        with turns:
            pass
        with turns:  # not tried again
            pass
    assert calls == [fcntl.LOCK_EX]
    assert not turns.supported
    assert any("no writer turns" in r.getMessage() for r in caplog.records)
