"""An operator makes the server forget a user: its filter, its latest position and its history go, in one
transaction with a snapshot, so that neither a crash nor the batch log brings it back."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select

from schemas.live import UserForgottenMessage
from server.errors import NotFoundError
from server.store.db import make_session_factory
from server.store.models import LatestPositionRow, PositionSnapshotRow
from tests.server.buildings.test_restart import (
    CROWD,
    _building,
    _estimates,
    _fresh_building,
    _groups,
    _pin_known,
)


def _stored(engine: object, user: str) -> int:
    with make_session_factory(engine)() as session:  # type: ignore[arg-type]
        return sum(
            int(session.execute(select(func.count()).where(table.user_id == user)).scalar_one())
            for table in (LatestPositionRow, PositionSnapshotRow)
        )


def test_a_forgotten_user_stays_forgotten_after_a_crash(database_url: str) -> None:
    engine = _fresh_building(database_url)
    building = _building(engine)  # no periodic snapshot: a crash replays every batch from the log
    _pin_known(building)
    groups = _groups(CROWD)
    for group in groups[: len(groups) // 2]:
        building.process(group)
    users = sorted(building.tracker.users)
    gone, kept = users[0], users[1:]
    assert _stored(engine, gone) > 0
    before = _estimates(building)

    assert building.users.forget(gone) == [UserForgottenMessage(user_id=gone)]
    assert gone not in building.tracker.users
    assert _stored(engine, gone) == 0
    assert {u: before[u] for u in kept} == _estimates(building)
    with pytest.raises(NotFoundError):
        building.users.forget(gone)

    building.abandon()  # a crash: nothing more is written
    rebuilt = _building(engine)
    assert sorted(rebuilt.tracker.users) == kept
    assert _estimates(rebuilt) == {u: before[u] for u in kept}
    with pytest.raises(NotFoundError):
        rebuilt.users.forget(gone)
    rebuilt.close()
    engine.dispose()
