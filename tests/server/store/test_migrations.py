"""Migrations build the schema the models describe, on SQLite and PostgreSQL, from empty or older states."""

from __future__ import annotations

from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import Engine, inspect

from server.store.db import make_engine
from server.store.migrate import current_revision, downgrade, head_revision, upgrade
from server.store.models import Base


def test_migrations_match_the_models(migrated_engine: Engine) -> None:
    with migrated_engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        diff = compare_metadata(context, Base.metadata)
    assert diff == [], f"models and migrations disagree; write a migration: {diff}"


def test_upgrade_from_empty_reaches_head(database_url: str) -> None:
    engine = make_engine(database_url)
    try:
        assert current_revision(engine) is None
        upgrade(engine)
        assert current_revision(engine) == head_revision(engine)
        tables = set(inspect(engine).get_table_names())
        assert set(Base.metadata.tables) <= tables
        upgrade(engine)  # idempotent at head
        assert current_revision(engine) == head_revision(engine)
    finally:
        engine.dispose()


def test_every_revision_downgrades_and_upgrades_again(migrated_engine: Engine) -> None:
    """An older database (any earlier revision, down to empty) upgrades to head."""
    downgrade(migrated_engine, "base")
    assert current_revision(migrated_engine) is None
    assert set(inspect(migrated_engine).get_table_names()) <= {"alembic_version"}
    upgrade(migrated_engine)
    assert current_revision(migrated_engine) == head_revision(migrated_engine)
