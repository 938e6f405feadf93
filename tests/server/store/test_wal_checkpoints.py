"""The write-ahead log is checkpointed by a thread of its own, not by the commits."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from sqlalchemy import Engine, text

from server.store.db import make_engine
from server.store.wal_checkpoints import (
    BackgroundCheckpoints,
    CheckpointStatus,
    checkpoint_in_background,
)

PAGE_FILLER = "x" * 3000  # about one 4 KiB page a row


def _fill(engine: Engine, rows: int, per_commit: int = 100) -> None:
    with engine.begin() as conn:
        conn.execute(text("CREATE TABLE IF NOT EXISTS filler (id INTEGER PRIMARY KEY, body TEXT)"))
    for first in range(0, rows, per_commit):
        with engine.begin() as conn:
            conn.execute(
                text("INSERT INTO filler (body) VALUES (:body)"),
                [{"body": PAGE_FILLER} for _ in range(min(per_commit, rows - first))],
            )


def _log_pages(path: Path) -> int:
    """Frames in the write-ahead log file (its header is 32 bytes, each frame a 24-byte header and a page)."""
    wal = path.with_name(path.name + "-wal")
    return (wal.stat().st_size - 32) // (24 + 4096) if wal.exists() else 0


def test_a_checkpoint_copies_the_whole_log(tmp_path: Path) -> None:
    path = tmp_path / "db.sqlite3"
    engine = make_engine(f"sqlite:///{path}")
    checkpoints = BackgroundCheckpoints(engine, period_s=3600.0)  # the thread will not run in this test
    try:
        _fill(engine, 500)  # below SQLite's own threshold: no commit has checkpointed
        status = checkpoints.checkpoint()
        assert status.checkpoints == 1
        assert not status.busy
        assert status.log_pages >= 500
        assert status.checkpointed_pages == status.log_pages
    finally:
        engine.dispose()
    assert not checkpoints.running


def test_the_log_stays_bounded_while_the_thread_copies_it(tmp_path: Path) -> None:
    """A writer that never pauses, with the thread copying beside it: the commits still start the log
    again at SQLite's threshold. (Had the commits left checkpointing to the thread alone, the log would
    hold all 6,000 pages: a checkpoint beside a busy writer never leaves the log wholly copied, which is
    when a writer starts it again.) The file keeps its high-water mark: ~1,050-2,250 pages in 40 runs
    here, as a commit's checkpoint that meets the thread's gives way to a later commit's."""
    path = tmp_path / "db.sqlite3"
    engine = make_engine(f"sqlite:///{path}")
    checkpoints = BackgroundCheckpoints(engine, period_s=0.005)
    try:
        _fill(engine, 6000, per_commit=50)
        assert checkpoints.status.checkpoints > 0
        assert checkpoints.status.failures == 0
        assert _log_pages(path) < 4000
    finally:
        engine.dispose()


def test_without_it_a_commit_checkpoints(tmp_path: Path) -> None:
    """The behaviour the thread takes over (and what the first test's threshold is measured against)."""
    path = tmp_path / "db.sqlite3"
    engine = make_engine(f"sqlite:///{path}")
    try:
        _fill(engine, 1500)
        with engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA wal_autocheckpoint").scalar() == 1000
            _busy, log_pages, _done = conn.exec_driver_sql("PRAGMA wal_checkpoint(PASSIVE)").one()
        assert log_pages < 1000
    finally:
        engine.dispose()


def test_the_thread_checkpoints_and_stops_with_the_engine(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    checkpoints = checkpoint_in_background(engine, 0.02)
    assert checkpoints is not None
    assert checkpoints.running
    _fill(engine, 50)
    deadline = time.monotonic() + 10.0
    while checkpoints.status.checkpointed_pages == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert checkpoints.status.checkpointed_pages > 0
    assert checkpoints.status.failures == 0
    engine.dispose()
    assert not checkpoints.running


def test_a_failed_checkpoint_is_counted_and_the_thread_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    calls = {"n": 0}
    real = BackgroundCheckpoints.checkpoint

    def flaky(self: BackgroundCheckpoints) -> CheckpointStatus:
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("disk on fire")
        return real(self)

    monkeypatch.setattr(BackgroundCheckpoints, "checkpoint", flaky)
    checkpoints = BackgroundCheckpoints(engine, period_s=0.02)
    deadline = time.monotonic() + 10.0
    while checkpoints.status.checkpoints == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert checkpoints.status.failures == 1
    assert checkpoints.status.checkpoints >= 1
    assert checkpoints.running
    engine.dispose()
    assert not checkpoints.running


def test_only_for_a_sqlite_file(tmp_path: Path) -> None:
    memory = make_engine("sqlite://")
    postgres = make_engine("postgresql+psycopg://postgres@127.0.0.1:5432/test")  # not connected
    file = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    try:
        assert checkpoint_in_background(memory, 1.0) is None
        assert checkpoint_in_background(postgres, 1.0) is None
        assert checkpoint_in_background(file, 0.0) is None  # 0: SQLite's own checkpoints
        with pytest.raises(ValueError, match="for SQLite"):
            BackgroundCheckpoints(postgres)
        with pytest.raises(ValueError, match="period_s"):
            BackgroundCheckpoints(file, period_s=-1.0)
    finally:
        for engine in (memory, postgres, file):
            engine.dispose()
