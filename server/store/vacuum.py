"""The server's own vacuum, for a PostgreSQL whose autovacuum is off.

A building deletes and updates rows all the time: the batch log (a row in, a row out, a thousand a second
at 1,000 phones), the history and batch ids past their retention, each user's latest position, the tracker's
snapshot (megabytes, rewritten every minute). PostgreSQL keeps a deleted or updated row's old version until
a vacuum marks its space reusable; autovacuum does that by default, but a server configured without it
grows without end (at 1,000 phones, ~110 MB a minute). Where autovacuum is off, a daemon thread applies
autovacuum's own rule to the server's tables every ``period_s``: a table whose dead rows pass
``THRESHOLD + SCALE x`` its live rows is vacuumed and analysed (``SKIP_LOCKED``: a table another process
is vacuuming is passed over, so several servers of a cluster never wait on each other).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from sqlalchemy import Engine, event, text

from server.store.models import Base

logger = logging.getLogger(__name__)

THRESHOLD = 50
SCALE = 0.2
"""PostgreSQL's defaults for ``autovacuum_vacuum_threshold`` and ``autovacuum_vacuum_scale_factor``."""
COST_DELAY_MS = 2
COST_LIMIT = 200
"""Autovacuum's throttle (``autovacuum_vacuum_cost_delay``, ``vacuum_cost_limit``): a manual VACUUM runs
unthrottled, and its reads and writes then compete with the building's commits."""


@dataclass
class VacuumStatus:
    checks: int = 0
    vacuums: int = 0
    failures: int = 0


class BackgroundVacuum:
    """Vacuum ``engine``'s tables that are due, every ``period_s``, until the engine is disposed."""

    def __init__(self, engine: Engine, period_s: float = 30.0) -> None:
        if engine.dialect.name != "postgresql":
            raise ValueError(f"the server's vacuum is for PostgreSQL, not {engine.dialect.name}")
        if period_s <= 0:
            raise ValueError("period_s must be > 0")
        self.engine = engine
        self.period_s = period_s
        self.status = VacuumStatus()
        self._stop = threading.Event()
        event.listen(engine, "engine_disposed", lambda _engine: self.stop())
        self._thread = threading.Thread(target=self._run, name="postgresql-vacuum", daemon=True)
        self._thread.start()

    def due(self) -> list[str]:
        """The server's tables whose dead rows, or their TOAST table's, pass autovacuum's rule (autovacuum
        weighs a TOAST table on its own: the tracker's snapshot is one row of megabytes, whose every rewrite
        leaves thousands of dead TOAST chunks and one dead row)."""
        tables = [t.name for t in Base.metadata.sorted_tables]
        with self.engine.connect() as conn:
            rows = conn.execute(
                text(
                    "SELECT s.relname FROM pg_stat_user_tables s JOIN pg_class c ON c.oid = s.relid "
                    "LEFT JOIN pg_stat_all_tables t ON t.relid = c.reltoastrelid "
                    "WHERE s.schemaname = current_schema() AND s.relname = ANY(:tables) "
                    "AND (s.n_dead_tup > :threshold + :scale * s.n_live_tup "
                    "OR coalesce(t.n_dead_tup, 0) > :threshold + :scale * coalesce(t.n_live_tup, 0))"
                ),
                {"tables": tables, "threshold": THRESHOLD, "scale": SCALE},
            )
            return sorted(str(name) for (name,) in rows)

    def vacuum_due(self) -> list[str]:
        """Vacuum (and analyse) the tables that are due now; the ones it vacuumed."""
        self.status.checks += 1
        due = self.due()
        if due:
            with self.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
                # throttled as autovacuum is: a manual VACUUM runs at full speed by default
                conn.exec_driver_sql(f"SET vacuum_cost_delay = {COST_DELAY_MS}")
                conn.exec_driver_sql(f"SET vacuum_cost_limit = {COST_LIMIT}")
                # VACUUM runs outside a transaction; names come from the models, quoted all the same
                quoted = ", ".join(conn.dialect.identifier_preparer.quote(name) for name in due)
                conn.exec_driver_sql(f"VACUUM (ANALYZE, SKIP_LOCKED) {quoted}")
            self.status.vacuums += len(due)
        return due

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.vacuum_due()
            except Exception:  # the next period tries again
                self.status.failures += 1
                logger.exception("vacuuming the server's PostgreSQL tables failed")


def autovacuum_is_on(engine: Engine) -> bool:
    with engine.connect() as conn:
        return str(conn.exec_driver_sql("SHOW autovacuum").scalar()).lower() == "on"


def vacuum_in_background(engine: Engine, period_s: float = 30.0) -> BackgroundVacuum | None:
    """The server's own vacuum where the database is PostgreSQL with autovacuum off (logged once); None
    elsewhere (SQLite reuses and returns pages itself, see ``server.store.db.reclaim_free_pages``)."""
    if engine.dialect.name != "postgresql" or autovacuum_is_on(engine):
        return None
    logger.warning(
        "autovacuum is off on this PostgreSQL server: crowdslam vacuums its own tables every %.0f s "
        "(turn autovacuum on: it keeps the whole database)",
        period_s,
    )
    return BackgroundVacuum(engine, period_s)
