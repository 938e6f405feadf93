"""``crowdslam migrate``: bring an empty or older database to the latest schema."""

from __future__ import annotations

import argparse

from sqlalchemy.engine import make_url


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--database-url",
        help="SQLAlchemy URL (default: CROWDSLAM_DATABASE_URL, else SQLite in CROWDSLAM_DATA_DIR)",
    )
    parser.add_argument("--revision", default="head", help="target revision (default: head)")


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from server.settings import get_settings
    from server.store.db import make_engine
    from server.store.migrate import current_revision, upgrade

    url = args.database_url or get_settings().resolved_database_url
    engine = make_engine(url)
    try:
        before = current_revision(engine)
        upgrade(engine, args.revision)
        after = current_revision(engine)
    finally:
        engine.dispose()
    shown = make_url(url).render_as_string(hide_password=True)
    print(f"{shown}: {before or 'empty'} -> {after}")
    return 0
