"""Migrations build the schema the models describe, on SQLite and PostgreSQL, from empty or older states."""

from __future__ import annotations

from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import Engine, inspect, text

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


def test_migration_0010_moves_the_logged_bodies_out_of_the_batch_ids(migrated_engine: Engine) -> None:
    """The bodies a restart would replay (applied, not yet covered) move to ``batch_log``; a late batch's
    body was never replayed and is not carried over; the ids stay."""
    downgrade(migrated_engine, "0009")
    with migrated_engine.begin() as connection:
        connection.execute(text("INSERT INTO buildings (id, name, rotation_rad) VALUES ('hq', 'HQ', 0.0)"))
        for k, (body, call) in enumerate([(b"applied", 3), (b"late", None), (None, 2)]):
            connection.execute(
                text(  # at revision 0009 the tracker call was named applied_round
                    "INSERT INTO batches (building_id, device_id, batch_id, seq, n_bytes, applied, "
                    "applied_round, body) VALUES ('hq', 'p', :b, :k, 1, :a, :r, :body)"
                ),
                {"b": f"b{k}", "k": k, "a": call is not None, "r": call, "body": body},
            )
    upgrade(migrated_engine)
    with migrated_engine.connect() as connection:
        ids = connection.execute(text("SELECT batch_id FROM batches ORDER BY batch_id")).scalars().all()
        log = connection.execute(text("SELECT tracker_call, body FROM batch_log")).all()
    assert ids == ["b0", "b1", "b2"]
    assert [(r, bytes(b)) for r, b in log] == [(3, b"applied")]
    downgrade(migrated_engine, "0009")  # and back: the body returns to its row
    with migrated_engine.connect() as connection:
        bodies = connection.execute(text("SELECT batch_id, body FROM batches ORDER BY batch_id")).all()
    assert [(b, None if body is None else bytes(body)) for b, body in bodies] == [
        ("b0", b"applied"),
        ("b1", None),
        ("b2", None),
    ]
