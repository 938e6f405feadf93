"""Database engines and sessions. SQLite is the embedded default; PostgreSQL by URL."""

from __future__ import annotations

import errno
import re
from collections.abc import Callable, Mapping, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

from sqlalchemy import Dialect, Engine, create_engine, event, func
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import make_url
from sqlalchemy.orm import InstrumentedAttribute, Session, sessionmaker


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    # takes effect only in a database with no table yet (a new one): freed pages can then be handed back to
    # the file system (``reclaim_free_pages``); an older database reuses them, and converts with VACUUM
    cursor.execute("PRAGMA auto_vacuum=INCREMENTAL")
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
    rows = insert_many_once(session, model, [values], conflict_columns, [returning])
    return rows[0][0] if rows else None


def insert_many_once(
    session: Session,
    model: type[Any],
    values: list[dict[str, Any]],
    conflict_columns: list[str],
    returning: list[InstrumentedAttribute[Any]],
) -> list[tuple[Any, ...]]:
    """One multi-row ``INSERT ... ON CONFLICT DO NOTHING RETURNING ...`` (rows of the same columns): the
    returned columns of the rows actually inserted, in no particular order (match them by key)."""
    if not values:
        return []
    mapped: Any = model  # a mapped class is hashable; typeshed's lru_cache wants it said
    stmt = _insert_once_statement(_dialect_name(session), mapped, tuple(conflict_columns), tuple(returning))
    shape = _values_clause(session.get_bind().dialect, stmt, tuple(values[0]))
    if shape is None:  # executemany, which SQLAlchemy batches as "insertmanyvalues"
        return [tuple(r) for r in session.connection().execute(stmt, values)]
    # The statement's text for this many rows, built once per count, and the rows' values straight to the
    # driver: SQLAlchemy's own batching processed each row's parameters in Python, as much again as the
    # insert
    head, row, tail, columns, positional = shape
    connection = session.connection()
    out: list[tuple[Any, ...]] = []
    per_statement = max(1, MAX_PARAMETERS // len(columns))
    for first in range(0, len(values), per_statement):
        rows = values[first : first + per_statement]
        sql = _rows_sql(head, row, tail, len(rows), positional)
        params: Any
        if positional:
            params = tuple(r[k] if f is None else f(r[k]) for r in rows for k, f in columns)
        else:
            params = {
                f"{k}_{i}": r[k] if f is None else f(r[k]) for i, r in enumerate(rows) for k, f in columns
            }
        out += [tuple(r) for r in connection.exec_driver_sql(sql, params)]
    return out


MAX_PARAMETERS = 900
"""Parameters of one statement at most: below SQLite's oldest limit (999) and PostgreSQL's (65,535)."""


@lru_cache(maxsize=64)
def _values_clause(
    dialect: Dialect, stmt: Any, columns: tuple[str, ...]
) -> tuple[str, str, str, tuple[tuple[str, _Conversion], ...], bool] | None:
    """The one-row statement's SQL cut around its row of values (before, the row, after), its parameters in
    order with their conversions, and whether they are positional; None when it cannot be cut so (a column
    computed by SQLAlchemy at execution, or text other than one ``VALUES (...)`` before ``ON CONFLICT``)."""
    compiled = _compiled(dialect, stmt, columns, returning=True)
    if compiled is None:
        return None
    sql, conversion, positional = compiled
    at, end = sql.find(" VALUES ("), sql.find(") ON CONFLICT ")
    if at < 0 or end < at or sql.count(" VALUES (") != 1:
        return None
    return sql[: at + 8], sql[at + 8 : end + 1], sql[end + 1 :], conversion, positional


_NAMED = re.compile(r"%\((\w+)\)s")


@lru_cache(maxsize=256)
def _rows_sql(head: str, row: str, tail: str, n: int, positional: bool) -> str:
    """The statement for ``n`` rows (named parameters take the row's index as a suffix)."""
    rows = [row] * n if positional else [_NAMED.sub(rf"%(\1_{i})s", row) for i in range(n)]
    return head + ", ".join(rows) + tail


@lru_cache(maxsize=64)
def _insert_once_statement(
    dialect: str, model: Any, conflict_columns: tuple[str, ...], returning: tuple[Any, ...]
) -> Any:
    """Built once per shape: building the statement (and its cache key) cost more than a group's rows."""
    stmt = _DIALECTS[dialect].insert(model).on_conflict_do_nothing(index_elements=list(conflict_columns))
    return stmt.returning(*returning)


_DIALECTS: dict[str, Any] = {"postgresql": postgresql, "sqlite": sqlite}


def _dialect_name(session: Session) -> str:
    dialect = session.get_bind().dialect.name
    if dialect not in _DIALECTS:
        raise NotImplementedError(f"unsupported database dialect {dialect!r}; use SQLite or PostgreSQL")
    return dialect


def upsert(
    session: Session,
    model: type[Any],
    values: list[dict[str, Any]],
    conflict_columns: list[str],
    keep_when_null: tuple[str, ...] = (),
) -> None:
    """One multi-row ``INSERT ... ON CONFLICT DO UPDATE``: every other given column takes the new value,
    except that a NULL in a ``keep_when_null`` column keeps the stored one."""
    if not values:
        return
    mapped: Any = model
    stmt = _upsert_statement(
        _dialect_name(session), mapped, tuple(values[0]), tuple(conflict_columns), tuple(keep_when_null)
    )
    execute_many(session, stmt, values)


def reclaim_free_pages(session: Session, max_pages: int, keep_fraction: float = 0.1) -> int:
    """On a SQLite database in incremental auto-vacuum, hand back to the file system up to ``max_pages`` of
    its free pages beyond ``keep_fraction`` of the pages in use (pages freed by deletions that new rows
    have not reused: the next inserts reuse those kept without growing the file). Elsewhere nothing:
    PostgreSQL's autovacuum makes dead rows' space reusable. Returns how many pages went."""
    if session.get_bind().dialect.name != "sqlite":
        return 0
    conn = session.connection()
    if conn.exec_driver_sql("PRAGMA auto_vacuum").scalar() != 2:  # 2: INCREMENTAL
        return 0
    free = int(conn.exec_driver_sql("PRAGMA freelist_count").scalar() or 0)
    pages = int(conn.exec_driver_sql("PRAGMA page_count").scalar() or 0)
    surplus = min(max_pages, free - int(keep_fraction * (pages - free)))
    if surplus <= 0:
        return 0
    # Python's sqlite3 steps a statement that returns no rows once, and each step of incremental_vacuum
    # frees one page: one execution per page (microseconds each)
    cursor = conn.connection.dbapi_connection.cursor()  # type: ignore[union-attr]
    try:
        for _ in range(surplus):
            cursor.execute("PRAGMA incremental_vacuum(1)")
    finally:
        cursor.close()
    return surplus


def is_disk_full(exc: BaseException) -> bool:
    """Whether the database refused a write for want of space: SQLite's ``SQLITE_FULL`` ("database or disk
    is full"), PostgreSQL's ``disk_full`` (SQLSTATE 53100), or the operating system's ``ENOSPC``."""
    cause = getattr(exc, "orig", None) or exc
    if getattr(cause, "sqlite_errorcode", None) == 13:  # SQLITE_FULL
        return True
    if getattr(cause, "sqlstate", None) == "53100":
        return True
    return isinstance(cause, OSError) and cause.errno == errno.ENOSPC


def execute_many(session: Session, stmt: Any, rows: Sequence[Mapping[str, Any]]) -> None:
    """``executemany`` of a statement built once (a module constant or a cached builder's), rows of the same
    columns, without SQLAlchemy's per-row parameter processing (as much again as the insert itself): the
    statement is compiled once per dialect and columns,
    and the rows go to the driver as tuples or mappings (by the dialect's parameter style), each value
    through the column type's conversion when it has one. Statements that return rows need ``execute``."""
    if not rows:
        return
    compiled = _compiled(session.get_bind().dialect, stmt, tuple(rows[0]))
    if compiled is None:
        session.connection().execute(stmt, list(rows))
        return
    sql, columns, positional = compiled
    if positional:
        params: list[Any] = [tuple(r[k] if f is None else f(r[k]) for k, f in columns) for r in rows]
    else:
        params = [{k: r[k] if f is None else f(r[k]) for k, f in columns} for r in rows]
    session.connection().exec_driver_sql(sql, params)


_Conversion = Callable[[Any], Any] | None


@lru_cache(maxsize=64)
def _compiled(
    dialect: Dialect, stmt: Any, columns: tuple[str, ...], returning: bool = False
) -> tuple[str, tuple[tuple[str, _Conversion], ...], bool] | None:
    """The statement's SQL for this dialect, its parameters in order with their conversions, and whether
    they are positional; None when this SQLAlchemy does not say (the caller falls back to ``execute``), or
    when the statement returns rows and the caller did not say it reads them (``returning``)."""
    compiled = stmt.compile(dialect=dialect, column_keys=list(columns))
    conversions = getattr(compiled, "_bind_processors", None)
    if conversions is None or set(compiled.binds) != set(columns):
        return None
    if compiled.effective_returning and not returning:
        return None
    order = compiled.positiontup if compiled.positional else list(compiled.binds)
    return str(compiled), tuple((k, conversions.get(k)) for k in order), bool(compiled.positional)


@lru_cache(maxsize=64)
def _upsert_statement(
    dialect: str,
    model: Any,
    columns: tuple[str, ...],
    conflict_columns: tuple[str, ...],
    keep_when_null: tuple[str, ...],
) -> Any:
    """Built once per shape (as ``_insert_once_statement``)."""
    stmt = _DIALECTS[dialect].insert(model)
    updates = {
        c: func.coalesce(stmt.excluded[c], getattr(model, c)) if c in keep_when_null else stmt.excluded[c]
        for c in columns
        if c not in conflict_columns
    }
    return stmt.on_conflict_do_update(index_elements=list(conflict_columns), set_=updates)
