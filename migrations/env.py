"""Alembic environment: runs on the engine handed in by ``server.store.migrate`` or on the settings' URL."""

from __future__ import annotations

from alembic import context
from sqlalchemy import Engine

from server.settings import get_settings
from server.store.db import make_engine
from server.store.models import Base

config = context.config
target_metadata = Base.metadata


def run_migrations_online() -> None:
    engine: Engine | None = config.attributes.get("engine")
    if engine is None:
        engine = make_engine(get_settings().resolved_database_url)
    with engine.begin() as connection:
        context.configure(
            connection=connection,
            target_metadata=target_metadata,
            render_as_batch=connection.dialect.name == "sqlite",
            compare_type=True,
        )
        context.run_migrations()


if context.is_offline_mode():
    raise SystemExit("offline (SQL script) migrations are not supported; run `crowdslam migrate`")
run_migrations_online()
