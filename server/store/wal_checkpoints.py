"""SQLite's write-ahead log copied into the database file by a thread of its own, ahead of the commits.

SQLite checkpoints in the commit that takes the log past 1,000 pages: that commit copies every page the
log holds into the database file (a read and a write each), syncs, and the next transaction starts the log
again from its beginning. A busy building fills that log every second or so, and the group whose commit
does the copying stalls behind it. Here a daemon thread runs a ``PASSIVE`` checkpoint every ``period_s``:
it waits for no reader or writer, and the sqlite3 module releases the GIL while it copies, so the copying
runs beside the batch path, and the commit that crosses 1,000 pages finds all but the last ``period_s``
of pages copied already. The commits keep SQLite's own threshold: the log is started again only by a
writer that finds it wholly copied, which a checkpoint running beside a busy writer never leaves it (with
the commits' checkpoints moved to a far larger threshold, the log grew to that threshold and the reads
slowed as it did).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from sqlalchemy import Engine, event

logger = logging.getLogger(__name__)


@dataclass
class CheckpointStatus:
    """The last checkpoint's outcome, as ``PRAGMA wal_checkpoint`` reports it."""

    checkpoints: int = 0
    busy: bool = False
    log_pages: int = 0
    checkpointed_pages: int = 0
    failures: int = 0


class BackgroundCheckpoints:
    """Checkpoint ``engine``'s database every ``period_s`` seconds until the engine is disposed (or
    ``stop``)."""

    def __init__(self, engine: Engine, period_s: float = 0.1) -> None:
        if period_s <= 0:
            raise ValueError("period_s must be > 0")
        if engine.dialect.name != "sqlite":
            raise ValueError(f"background checkpoints are for SQLite, not {engine.dialect.name}")
        self.engine = engine
        self.period_s = period_s
        self.status = CheckpointStatus()
        self._stop = threading.Event()
        event.listen(engine, "engine_disposed", self._on_dispose)
        self._thread = threading.Thread(target=self._run, name="sqlite-checkpoints", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def checkpoint(self) -> CheckpointStatus:
        """One ``PASSIVE`` checkpoint now (the thread's step; also callable directly)."""
        with self.engine.connect() as conn:
            busy, log_pages, checkpointed = conn.exec_driver_sql("PRAGMA wal_checkpoint(PASSIVE)").one()
        s = self.status
        s.checkpoints += 1
        s.busy, s.log_pages, s.checkpointed_pages = bool(busy), int(log_pages), int(checkpointed)
        return s

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()

    def _on_dispose(self, _engine: Engine) -> None:
        self.stop()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.checkpoint()
            except Exception:  # the next period tries again; the commits checkpoint as they always did
                self.status.failures += 1
                logger.exception("checkpointing the SQLite write-ahead log failed")


def checkpoint_in_background(engine: Engine, period_s: float) -> BackgroundCheckpoints | None:
    """Background checkpoints for a SQLite database file; None for other engines (PostgreSQL, an
    in-memory SQLite: no write-ahead log) and when ``period_s`` is 0 (SQLite's own checkpoints)."""
    database = engine.url.database
    if period_s == 0 or engine.dialect.name != "sqlite" or not database or database == ":memory:":
        return None
    return BackgroundCheckpoints(engine, period_s)
