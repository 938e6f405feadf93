"""Turns at SQLite's single write lock for the buildings that share one database file.

A building's group of batches is one transaction: it takes SQLite's write lock at its first insert (the
batch rows, which decide retries by the unique constraint) and keeps it through the tracker's update to the
commit. With several buildings on one file, in threads or in processes of their own, the others' groups
wait for it in SQLite's busy handler, which sleeps 1, 2, 5, 10, 15, 20, 25, ... 100 ms between tries
instead of waking when the lock frees, and a writer that just committed often takes the lock again before a
sleeper wakes: two buildings of 500 load-bench phones each had p99 458 ms where one building of 1,000 had
13 ms. Here each building's batch transaction first takes an exclusive ``flock`` on a file beside the
database, which the kernel hands to a waiter as soon as it is released; the groups still take turns (one
writer at a time is SQLite's), but none sleeps past its turn. Other writers (the operator API, snapshot
compression) are rare and keep SQLite's busy handler. A process killed while it holds a turn gives it up
with its open files. PostgreSQL locks rows, and needs none of this.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

from sqlalchemy import Engine

logger = logging.getLogger(__name__)


class WriterTurns:
    """An exclusive ``flock`` on ``path``, taken and released around each write transaction, on a file
    opened for that turn alone: two buildings in one process take turns as two in two processes do
    (``flock`` locks belong to an open file, not to a process), and a session dropped without closing
    holds no file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file: BinaryIO | None = None
        # False once the file system refused ``flock`` (some network file systems): the transactions then wait
        # in SQLite's busy handler, as they did before the turns.
        self.supported = True

    def __enter__(self) -> WriterTurns:
        if self._file is not None:
            raise RuntimeError(f"a turn at {self.path} is already held by this holder")
        if not self.supported:
            return self
        file = self.path.open("ab")
        try:
            fcntl.flock(file.fileno(), fcntl.LOCK_EX)  # releases the GIL while it waits
        except OSError as exc:
            file.close()
            self.supported = False
            logger.warning(
                "no writer turns at %s (%s): SQLite's busy handler decides who writes", self.path, exc
            )
            return self
        except BaseException:
            file.close()
            raise
        self._file = file
        return self

    def __exit__(
        self, _type: type[BaseException] | None, _value: BaseException | None, _tb: TracebackType | None
    ) -> None:
        file, self._file = self._file, None
        if file is not None:
            file.close()  # closing the file releases its lock


def writer_turns(engine: Engine) -> WriterTurns | contextlib.nullcontext[None]:
    """Turns for a SQLite file database (``<database>-writers.lock`` beside it); nothing to take for other
    databases, or for SQLite in memory (one connection, one process)."""
    url = engine.url
    if url.get_backend_name() != "sqlite" or not url.database or url.database == ":memory:":
        return contextlib.nullcontext()
    return WriterTurns(Path(url.database + "-writers.lock"))
