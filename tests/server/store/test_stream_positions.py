"""A building's batch-stream position only moves forward, in the caller's transaction. On SQLite and
PostgreSQL."""

from __future__ import annotations

import pytest
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from server.store import repositories as repo
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade
from server.store.models import BuildingRow


def _advance_and_commit(session: Session, building_id: str, sequence: int) -> None:
    repo.advance_stream_position(session, building_id, sequence)
    session.commit()


def test_the_position_moves_forward_only_and_with_its_transaction(database_url: str) -> None:
    engine = make_engine(database_url)
    upgrade(engine)
    sessions = make_session_factory(engine)
    try:
        with sessions.begin() as session:
            session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
            session.add(BuildingRow(id="annex", name="Annex", rotation_rad=0.0))
        with sessions.begin() as session:
            assert repo.stream_position(session, "hq") == 0
            repo.advance_stream_position(session, "hq", 5)
            repo.advance_stream_position(session, "hq", 7)
        for stale in (7, 3):
            with pytest.raises(repo.StaleStreamPositionError, match="up to 7"), sessions.begin() as session:
                repo.advance_stream_position(session, "hq", stale)
        # a transaction that fails after advancing leaves the position where it was
        session = sessions()
        repo.advance_stream_position(session, "hq", 9)
        session.rollback()  # the batches' commit failed
        session.close()
        with sessions() as session:
            assert repo.stream_position(session, "hq") == 7
            assert repo.stream_position(session, "annex") == 0
        # two workers both applying a building's first batch: one of them fails on the key
        first, second = sessions(), sessions()
        try:
            repo.advance_stream_position(first, "annex", 1)
            first.commit()
            with pytest.raises((IntegrityError, repo.StaleStreamPositionError)):
                _advance_and_commit(second, "annex", 1)
        finally:
            first.close()
            second.close()
        # a building's position goes with it
        with sessions.begin() as session:
            session.delete(session.get(BuildingRow, "hq"))
        with sessions() as session:
            assert repo.stream_position(session, "hq") == 0
    finally:
        engine.dispose()
