"""History retention, on both databases: each user's latest position lives apart from the history (GET
/positions reads one row per user), old history and old batch ids are pruned in bounded chunks by the
time the server stored them, and the batch log a restart replays is never pruned. Migration 0003 fills
the latest positions of a database that has history."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

from sqlalchemy import Engine, func, insert, select

from server.store import repositories as repo
from server.store.batches import AcceptedBatch, insert_batches_once
from server.store.db import make_session_factory, reclaim_free_pages
from server.store.migrate import downgrade, upgrade
from server.store.models import BatchRow, BuildingRow, LatestPositionRow, PositionSnapshotRow

T0 = 1_700_000_000_000


def _position(user: str, t_ms: int, stored_at_ms: int | None) -> dict[str, object]:
    row: dict[str, object] = {
        "building_id": "hq", "user_id": user, "device_id": user, "t_ms": t_ms, "x_m": float(t_ms % 97),
        "y_m": 1.0, "cov_xx": 1.0, "cov_xy": 0.0, "cov_yy": 1.0, "heading_rad": 0.0, "floor": 0,
        "source": "dynamicslam",
    }  # fmt: skip
    if stored_at_ms is not None:
        row["stored_at_ms"] = stored_at_ms
    return row


def _count(engine: Engine, table: type[PositionSnapshotRow] | type[BatchRow]) -> int:
    with make_session_factory(engine)() as session:
        return int(session.execute(select(func.count()).select_from(table)).scalar_one())


def test_latest_positions_are_one_row_per_user(migrated_engine: Engine) -> None:
    sessions = make_session_factory(migrated_engine)
    with sessions.begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
        session.flush()
        for k in range(3):
            repo.add_positions(session, [_position("a", T0 + k, T0), _position("b", T0 + 10 * k, T0)])
    with sessions() as session:
        latest = repo.latest_positions(session, "hq")
    assert [(r.user_id, r.t_ms) for r in latest] == [("a", T0 + 2), ("b", T0 + 20)]
    assert _count(migrated_engine, PositionSnapshotRow) == 6


def test_old_history_and_batch_ids_are_pruned_in_chunks_but_never_the_log(migrated_engine: Engine) -> None:
    sessions = make_session_factory(migrated_engine)
    now = datetime.now(UTC)
    with sessions.begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
        session.flush()
        # phone times are old (a replayed recording): storage time decides
        repo.add_positions(session, [_position("a", T0 - 10**10, T0 - 1 - k) for k in range(5)])
        repo.add_positions(session, [_position("a", T0 - 10**10, T0 + 5)])
        stored = [
            AcceptedBatch(
                "hq",
                "p",
                f"b{k}",
                k,
                None,
                None,
                10,
                body=b"{}" if k == 4 else None,
                tracker_call=k if k == 4 else None,
            )
            for k in range(5)
        ]
        insert_batches_once(session, stored)
        session.execute(
            BatchRow.__table__.update().values(received_at=now - timedelta(days=3))  # type: ignore[attr-defined]
        )
        insert_batches_once(session, [AcceptedBatch("hq", "p", "fresh", 9, None, None, 10)])
    with sessions.begin() as session:
        assert repo.prune_history(session, "hq", T0, now - timedelta(days=2), limit=3) == (3, 3)
    with sessions.begin() as session:
        assert repo.prune_history(session, "hq", T0, now - timedelta(days=2), limit=3) == (2, 1)
    with sessions.begin() as session:
        assert repo.prune_history(session, "hq", T0, now - timedelta(days=2), limit=3) == (0, 0)
        assert repo.prune_history(session, "hq", None, None, limit=3) == (0, 0)
    with sessions() as session:
        left = session.execute(select(BatchRow.batch_id).order_by(BatchRow.batch_id)).scalars().all()
        assert left == ["b4", "fresh"]  # the logged body and the recent id stay
        assert session.execute(select(PositionSnapshotRow.stored_at_ms)).scalars().all() == [T0 + 5]
        assert len(repo.latest_positions(session, "hq")) == 1  # the latest position is never pruned


def test_migration_0003_fills_the_latest_positions_from_history(migrated_engine: Engine) -> None:
    downgrade(migrated_engine, "0002")
    with migrated_engine.begin() as connection:
        connection.execute(insert(BuildingRow.__table__).values(id="hq", name="HQ", rotation_rad=0.0))  # type: ignore[arg-type]
        for user, t in (("a", T0), ("a", T0 + 5), ("b", T0 + 1)):
            row = _position(user, t, None)
            connection.execute(insert(PositionSnapshotRow.__table__).values(**row))  # type: ignore[arg-type]
    upgrade(migrated_engine)
    with make_session_factory(migrated_engine)() as session:
        latest = session.execute(select(LatestPositionRow.user_id, LatestPositionRow.t_ms)).all()
        stored = session.execute(select(PositionSnapshotRow.stored_at_ms)).scalars().all()
    assert sorted(latest) == [("a", T0 + 5), ("b", T0 + 1)]
    assert sorted(stored) == [T0, T0 + 1, T0 + 5]


def test_a_new_sqlite_database_hands_freed_pages_back_beyond_a_slack(migrated_engine: Engine) -> None:
    sessions = make_session_factory(migrated_engine)
    with sessions.begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
        session.flush()
        repo.add_positions(session, [_position(f"u{k}", T0 + k, T0) for k in range(20_000)])
    if migrated_engine.dialect.name != "sqlite":
        with sessions.begin() as session:
            assert reclaim_free_pages(session, 10**6) == 0  # PostgreSQL's autovacuum's business
        return
    path = Path(str(migrated_engine.url.database))
    with sessions.begin() as session:
        assert session.connection().exec_driver_sql("PRAGMA auto_vacuum").scalar() == 2
        assert reclaim_free_pages(session, 10**6) == 0  # nothing freed yet
        repo.prune_history(session, "hq", T0 + 1, None, limit=10**6)  # stored before: all of the history
        session.execute(LatestPositionRow.__table__.delete())  # type: ignore[attr-defined]
    full = path.stat().st_size
    with sessions.begin() as session:
        free = int(session.connection().exec_driver_sql("PRAGMA freelist_count").scalar() or 0)
        assert free > 100
        assert reclaim_free_pages(session, 50) == 50  # bounded per call
        reclaimed = reclaim_free_pages(session, 10**6, keep_fraction=0.1)
        pages = int(session.connection().exec_driver_sql("PRAGMA page_count").scalar() or 0)
        left = int(session.connection().exec_driver_sql("PRAGMA freelist_count").scalar() or 0)
    assert reclaimed > 0
    assert left <= 0.1 * (pages - left) + 1
    migrated_engine.dispose()  # the checkpoint that truncates the file comes with the last connection
    assert path.stat().st_size < full / 2
