"""Database engines and sessions. SQLite is the embedded default; PostgreSQL by URL."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import make_url
from sqlalchemy.orm import InstrumentedAttribute, Session, sessionmaker


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA busy_timeout=5000")
    cursor.close()


def make_engine(url: str, **kwargs: Any) -> Engine:
    """An engine for ``url``. For SQLite the parent folder is created and foreign keys are enforced."""
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        if parsed.database and parsed.database != ":memory:":
            Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, **kwargs)
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    kwargs.setdefault("pool_pre_ping", True)
    return create_engine(url, **kwargs)


def make_session_factory(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)


def insert_once(
    session: Session,
    model: type[Any],
    values: dict[str, Any],
    conflict_columns: list[str],
    returning: InstrumentedAttribute[Any],
) -> Any | None:
    """``INSERT ... ON CONFLICT DO NOTHING RETURNING <column>``: the value of the new row, or None when the
    conflict columns already exist. The database decides atomically (never check-then-insert)."""
    dialect = session.get_bind().dialect.name
    if dialect == "postgresql":
        pg_stmt = (
            postgresql.insert(model).values(values).on_conflict_do_nothing(index_elements=conflict_columns)
        )
        return session.execute(pg_stmt.returning(returning)).scalar_one_or_none()
    if dialect == "sqlite":
        lite_stmt = (
            sqlite.insert(model).values(values).on_conflict_do_nothing(index_elements=conflict_columns)
        )
        return session.execute(lite_stmt.returning(returning)).scalar_one_or_none()
    raise NotImplementedError(f"unsupported database dialect {dialect!r}; use SQLite or PostgreSQL")
