"""``execute_many`` sends rows straight to the driver: on both databases they must be stored exactly as
SQLAlchemy's own ``execute`` stores them, upserts included, and a statement it cannot take (one that returns
rows) must still run, through ``execute``."""

from __future__ import annotations

from sqlalchemy import Engine, delete, insert, select

from server.store import repositories as repo
from server.store.db import _compiled, execute_many, make_session_factory, upsert
from server.store.models import BuildingRow, DeviceRow, LatestPositionRow, PositionSnapshotRow

T0 = 1_700_000_000_000


def _position(user: str, t_ms: int, x: float) -> dict[str, object]:
    return {
        "stored_at_ms": t_ms + 5,
        "building_id": "hq",
        "user_id": user,
        "device_id": f"phone-{user}",
        "t_ms": t_ms,
        "x_m": x,
        "y_m": -x / 3.0,
        "cov_xx": 0.64,
        "cov_xy": 1e-17,
        "cov_yy": 0.81,
        "heading_rad": -3.1,
        "floor": -2,
        "source": "dynamicslam",
    }


def _history(engine: Engine) -> list[tuple[object, ...]]:
    with make_session_factory(engine)() as session:
        rows = session.execute(
            select(PositionSnapshotRow).order_by(PositionSnapshotRow.user_id, PositionSnapshotRow.t_ms)
        ).scalars()
        return [
            (
                r.user_id,
                r.device_id,
                r.t_ms,
                r.x_m,
                r.y_m,
                r.cov_xy,
                r.heading_rad,
                r.floor,
                r.source,
                r.stored_at_ms,
            )
            for r in rows
        ]


def test_rows_are_stored_as_sqlalchemy_stores_them(migrated_engine: Engine) -> None:
    sessions = make_session_factory(migrated_engine)
    with sessions.begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
    rows = [_position(u, T0 + k, 0.1 * k + 1 / 3) for k in range(3) for u in ("a", "b")]
    with sessions.begin() as session:
        execute_many(session, repo._POSITIONS_INSERT, rows[:3])
    stored = _history(migrated_engine)
    with sessions.begin() as session:  # the same rows again, through SQLAlchemy's parameter processing
        session.execute(delete(PositionSnapshotRow))
        session.connection().execute(insert(PositionSnapshotRow), rows[:3])
    assert _history(migrated_engine) == stored
    assert len(stored) == 3
    assert stored[0][3] == 1 / 3  # floats exactly

    with sessions.begin() as session:  # the latest position per user: inserted, then updated
        repo.add_positions(session, rows)
    with sessions() as session:
        latest = {r.user_id: (r.t_ms, r.x_m) for r in session.execute(select(LatestPositionRow)).scalars()}
    assert latest == {"a": (T0 + 2, 0.2 + 1 / 3), "b": (T0 + 2, 0.2 + 1 / 3)}
    assert len(_history(migrated_engine)) == 3 + len(rows)


def test_upserts_keep_a_stored_value_where_asked(migrated_engine: Engine) -> None:
    sessions = make_session_factory(migrated_engine)
    with sessions.begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
    first = {"building_id": "hq", "id": "p1", "user_id": "u1", "ble_advertised_id": "ble-1", "last_seq": 3}
    with sessions.begin() as session:
        upsert(session, DeviceRow, [first], ["building_id", "id"], keep_when_null=("ble_advertised_id",))
    with sessions.begin() as session:
        upsert(
            session,
            DeviceRow,
            [first | {"ble_advertised_id": None, "last_seq": 9}],
            ["building_id", "id"],
            keep_when_null=("ble_advertised_id",),
        )
    with sessions() as session:
        device = session.execute(select(DeviceRow)).scalar_one()
    assert (device.ble_advertised_id, device.last_seq) == ("ble-1", 9)


def test_a_statement_that_returns_rows_goes_through_execute(migrated_engine: Engine) -> None:
    returning = insert(BuildingRow).returning(BuildingRow.id)
    columns = ("id", "name", "rotation_rad")
    assert _compiled(migrated_engine.dialect, returning, columns) is None
    assert (
        _compiled(migrated_engine.dialect, repo._POSITIONS_INSERT, tuple(_position("a", T0, 0.0))) is not None
    )
    sessions = make_session_factory(migrated_engine)
    with sessions.begin() as session:
        execute_many(session, returning, [{"id": "hq", "name": "HQ", "rotation_rad": 0.5}])
        execute_many(session, returning, [])
    with sessions() as session:
        assert session.execute(select(BuildingRow.rotation_rad)).scalar_one() == 0.5
