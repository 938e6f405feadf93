"""A retried batch is detected by the unique constraint, on both databases."""

from __future__ import annotations

import threading
from dataclasses import replace

import pytest
from sqlalchemy import Engine, func, insert, select
from sqlalchemy.exc import IntegrityError

from server.store.batches import (
    AcceptedBatch,
    _values,
    clear_covered_bodies,
    find_batch,
    insert_batch_once,
    insert_batches_once,
    logged_batches,
)
from server.store.db import _insert_once_statement, _values_clause, make_session_factory
from server.store.models import BatchLogRow, BatchRow, BuildingRow
from server.store.repositories import save_tracker_snapshot


def _batch(batch_id: str = "b-1", device_id: str = "phone-1", seq: int = 1) -> AcceptedBatch:
    return AcceptedBatch("hq", device_id, batch_id, seq, 1700000000000, 1700000000900, 1234)


def _with_building(engine: Engine) -> None:
    with make_session_factory(engine).begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))


def _count(engine: Engine) -> int:
    with make_session_factory(engine)() as session:
        return int(session.execute(select(func.count()).select_from(BatchRow)).scalar_one())


def test_retry_is_detected_by_the_constraint(migrated_engine: Engine) -> None:
    _with_building(migrated_engine)
    sessions = make_session_factory(migrated_engine)
    with sessions.begin() as session:
        first = insert_batch_once(session, _batch())
    with sessions.begin() as session:
        again = insert_batch_once(session, _batch(seq=99))  # same batch id, whatever else differs
    assert first is not None
    assert again is None
    assert _count(migrated_engine) == 1
    with sessions() as session:
        row = find_batch(session, "hq", "phone-1", "b-1")
        assert row is not None
        assert row.seq == 1
        assert not row.applied


def test_same_batch_id_on_another_device_is_a_different_batch(migrated_engine: Engine) -> None:
    _with_building(migrated_engine)
    with make_session_factory(migrated_engine).begin() as session:
        assert insert_batch_once(session, _batch(device_id="phone-1")) is not None
        assert insert_batch_once(session, _batch(device_id="phone-2")) is not None
    assert _count(migrated_engine) == 2


def test_concurrent_retries_accept_exactly_one(migrated_engine: Engine) -> None:
    _with_building(migrated_engine)
    sessions = make_session_factory(migrated_engine)
    results: list[int | None] = []
    errors: list[BaseException] = []
    barrier = threading.Barrier(4)

    def post() -> None:
        try:
            barrier.wait()
            with sessions.begin() as session:
                results.append(insert_batch_once(session, _batch()))
        except BaseException as error:  # surfaced below
            errors.append(error)

    threads = [threading.Thread(target=post) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=30)
    assert not errors, errors
    assert sum(r is not None for r in results) == 1
    assert _count(migrated_engine) == 1


def test_rolled_back_batch_can_be_sent_again(migrated_engine: Engine) -> None:
    """If applying a batch fails, its row goes with the transaction, so the phone's retry is accepted."""
    _with_building(migrated_engine)
    sessions = make_session_factory(migrated_engine)

    def apply_and_fail() -> None:
        with sessions.begin() as session:
            assert insert_batch_once(session, _batch()) is not None
            raise RuntimeError("filter update failed")

    with pytest.raises(RuntimeError, match="filter update failed"):
        apply_and_fail()
    with sessions.begin() as session:
        retried = replace(_batch(), body=b"{}", tracker_call=7)
        assert insert_batch_once(session, retried) is not None
    with sessions() as session:
        row = find_batch(session, "hq", "phone-1", "b-1")
        assert row is not None
        assert row.applied
        assert [(b.tracker_call, b.body) for b in logged_batches(session, "hq")] == [(7, b"{}")]


def test_a_late_batch_is_stored_but_not_logged_for_replay(migrated_engine: Engine) -> None:
    _with_building(migrated_engine)
    sessions = make_session_factory(migrated_engine)
    with sessions.begin() as session:
        assert insert_batch_once(session, replace(_batch(), body=b"{}")) is not None
    with sessions() as session:
        row = find_batch(session, "hq", "phone-1", "b-1")
        assert row is not None
        assert not row.applied
        assert row.tracker_call is None
        assert logged_batches(session, "hq") == []


def test_the_log_is_cleared_a_chunk_at_a_time_up_to_the_snapshots_call_only(migrated_engine: Engine) -> None:
    """Bodies the snapshot in SQL covers go, at most ``limit`` per call; those after its tracker call stay
    (they are what a restart replays), and without a snapshot no applied body goes."""
    _with_building(migrated_engine)
    sessions = make_session_factory(migrated_engine)
    batches = [replace(_batch(f"b-{r}", seq=r), body=b"{}", tracker_call=r) for r in range(1, 6)]
    with sessions.begin() as session:
        insert_batches_once(session, batches)
        assert clear_covered_bodies(session, "hq") == 0  # no snapshot: nothing is covered
        save_tracker_snapshot(session, "hq", 1, 3, b"state")
    with sessions.begin() as session:
        assert clear_covered_bodies(session, "hq", limit=2) == 2
        assert clear_covered_bodies(session, "hq", limit=2) == 1
        assert clear_covered_bodies(session, "hq", limit=2) == 0
    with sessions() as session:
        assert [b.tracker_call for b in logged_batches(session, "hq")] == [4, 5]
        assert [b.tracker_call for b in logged_batches(session, "hq", after_call=4)] == [5]
    with sessions.begin() as session:
        save_tracker_snapshot(session, "hq", 1, 5, b"state")
        assert clear_covered_bodies(session, "hq") == 2
    assert _count(migrated_engine) == 5  # the ids stay: retries are still recognised


def test_the_log_holds_bodies_compressed_and_reads_back_uncompressed_ones_as_they_are(
    migrated_engine: Engine,
) -> None:
    """A body is logged as a zstd frame (a batch's JSON shrinks to a fraction) and read back byte for byte; a
    body logged uncompressed, as before compression, is read as it is."""
    _with_building(migrated_engine)
    sessions = make_session_factory(migrated_engine)
    body = (
        b'{"device_id":"phone-1","batch_id":"b-1","steps":['
        + b",".join(
            b'{"t_ms":%d,"length_m":0.7,"heading_rad":1.5}' % (1700000000000 + 500 * k) for k in range(20)
        )
        + b"]}"
    )
    with sessions.begin() as session:
        first = insert_batch_once(session, replace(_batch("b-1"), body=body, tracker_call=1))
        old = insert_batch_once(session, replace(_batch("b-2", seq=2), tracker_call=2))
        assert first is not None
        assert old is not None
        session.execute(
            insert(BatchLogRow).values(batch_row_id=old, building_id="hq", tracker_call=2, body=b"{}")
        )
    with sessions() as session:
        stored = session.execute(
            select(BatchLogRow.body).where(BatchLogRow.batch_row_id == first)
        ).scalar_one()
        assert bytes(stored).startswith(b"\x28\xb5\x2f\xfd")
        assert len(stored) < len(body) / 3
        assert [(b.tracker_call, b.body) for b in logged_batches(session, "hq")] == [(1, body), (2, b"{}")]


def test_batch_for_unknown_building_violates_the_foreign_key(migrated_engine: Engine) -> None:
    with pytest.raises(IntegrityError), make_session_factory(migrated_engine).begin() as session:
        insert_batch_once(session, _batch())
    assert _count(migrated_engine) == 0


def test_a_large_group_is_inserted_in_several_statements_with_every_retry_found(
    migrated_engine: Engine,
) -> None:
    """More rows than one statement's parameters take: each new batch gets its row id, a repeat within the
    group or of an earlier group gets None, and every column (the applied flag, NULL times) is stored."""
    _with_building(migrated_engine)
    sessions = make_session_factory(migrated_engine)
    with sessions.begin() as session:
        assert insert_batches_once(session, [_batch("b-early", device_id="phone-7")])[0] is not None
    batches = [
        replace(_batch(f"b-{k}", device_id=f"phone-{k % 9}", seq=k), tracker_call=k if k % 3 else None)
        for k in range(250)
    ]
    batches[40] = replace(batches[3], seq=999)  # a repeat within the group
    batches.append(replace(_batch("b-early", device_id="phone-7"), seq=5))  # a retry of an earlier group
    batches[100] = replace(batches[100], t_first_ms=None, t_last_ms=None)
    with sessions.begin() as session:
        ids = insert_batches_once(session, batches)
    assert ids[40] is None
    assert ids[-1] is None
    fresh = [i for k, i in enumerate(ids) if k not in (40, len(ids) - 1)]
    assert None not in fresh
    assert len(set(fresh)) == len(fresh) == 249
    assert _count(migrated_engine) == 250
    statement = _insert_once_statement(
        migrated_engine.dialect.name, BatchRow, ("building_id", "device_id", "batch_id"),
        (BatchRow.id, BatchRow.device_id, BatchRow.batch_id),
    )  # fmt: skip
    columns = tuple(_values(batches[0]))
    assert (
        _values_clause(migrated_engine.dialect, statement, columns) is not None
    )  # not SQLAlchemy's batching
    with sessions() as session:
        stored = {
            (r.device_id, r.batch_id): r
            for r in session.execute(select(BatchRow).where(BatchRow.batch_id != "b-early")).scalars()
        }
        for k, b in enumerate(batches[:-1]):
            if k == 40:
                continue
            row = stored[(b.device_id, b.batch_id)]
            assert row.id == ids[k]
            assert (row.seq, row.applied, row.tracker_call) == (
                b.seq,
                b.tracker_call is not None,
                b.tracker_call,
            )
            assert (row.t_first_ms, row.t_last_ms) == (b.t_first_ms, b.t_last_ms)
