"""The device ledger: late batches, one tracker call per user's batch in a group, which device rows SQL must
learn when, and sequence numbers carried across a restart by the batch log."""

from __future__ import annotations

from typing import Any

from schemas.sensors import SensorBatch
from server.buildings.ledger import DeviceLedger
from server.buildings.submissions import BatchHeader


def _batch(
    device: str, seq: int, user: str | None = None, ble: str | None = None, install: int | None = None
) -> BatchHeader:
    body: dict[str, Any] = {
        "building_id": "hq",
        "device_id": device,
        "batch_id": f"{device}-{install}-{seq}",
        "seq": seq,
    }
    if install is not None:
        body["install_ms"] = install
    if user is not None:
        body["user_id"] = user
    if ble is not None:
        body["ble_advertised_id"] = ble
    return BatchHeader.of(SensorBatch.model_validate(body))


def test_plan_marks_late_batches_and_gives_each_user_one_batch_per_call() -> None:
    ledger = DeviceLedger("hq", {"p1": ("p1", None, 5, None)})
    batches = [
        _batch("p1", 5),
        _batch("p1", 7),
        _batch("p2", 0),
        _batch("p1", 6),
        _batch("p1", 8),
        _batch("p2", 1),
    ]
    assert ledger.plan(batches) == [None, 1, 1, None, 2, 2]
    assert ledger.last_seq("p1") == 5  # planning records nothing


def test_two_devices_of_one_user_share_its_calls() -> None:
    ledger = DeviceLedger("hq", {})
    batches = [_batch("watch", 0, user="ann"), _batch("phone", 0, user="ann")]
    assert ledger.plan(batches) == [1, 2]


def test_device_rows_are_written_when_a_device_appears_or_changes_and_seqs_at_snapshots() -> None:
    ledger = DeviceLedger("hq", {"p1": ("p1", "ble-1", 3, None)})
    assert ledger.applied(_batch("p1", 4)) is None  # same user, no Bluetooth id: nothing new for SQL
    assert ledger.applied(_batch("p1", 5, ble="ble-1")) is None
    row = ledger.applied(_batch("p1", 6, ble="ble-9"))
    assert row == {
        "building_id": "hq",
        "id": "p1",
        "user_id": "p1",
        "ble_advertised_id": "ble-9",
        "last_seq": 6,
        "install_ms": None,
    }
    new = ledger.applied(_batch("p2", 0))
    assert new is not None
    assert new["last_seq"] == 0
    ledger.saved([row, new])
    assert ledger.unsaved_rows() == []
    ledger.applied(_batch("p1", 7))
    unsaved = ledger.unsaved_rows()
    assert [(r["id"], r["last_seq"], r["ble_advertised_id"]) for r in unsaved] == [("p1", 7, "ble-9")]
    assert ledger.unsaved_rows() == unsaved  # until they are committed
    ledger.saved(unsaved)
    assert ledger.unsaved_rows() == []


def test_replayed_batches_carry_sequence_numbers_across_a_restart() -> None:
    ledger = DeviceLedger("hq", {"p1": ("p1", None, 3, None)})  # SQL as of the last snapshot
    for seq in (4, 5, 6):
        ledger.replayed(_batch("p1", seq))
    ledger.replayed(_batch("p2", 2))
    assert ledger.last_seq("p1") == 6
    assert ledger.plan([_batch("p1", 5), _batch("p2", 2), _batch("p2", 3)]) == [None, None, 1]
    assert {r["id"]: r["last_seq"] for r in ledger.unsaved_rows()} == {"p1": 6, "p2": 2}


A, B = 1_767_225_600_000, 1_767_312_000_000  # two installs of the app, a day apart


def test_a_later_install_starts_the_count_again_and_an_earlier_one_is_late() -> None:
    ledger = DeviceLedger("hq", {"p1": ("p1", None, 2**62, A)})  # at the end of its sequence numbers
    assert ledger.plan([_batch("p1", 2**62, install=A)]) == [None]
    # reinstalled: seq from 0 again, in order within the new install; the old install's batches are late
    plan = ledger.plan([_batch("p1", 0, install=B), _batch("p1", 1, install=B), _batch("p1", 9, install=A)])
    assert plan == [1, 2, None]
    for b in (_batch("p1", 0, install=B), _batch("p1", 1, install=B)):
        ledger.applied(b)
    assert ledger.last_seq("p1") == 1
    assert ledger.plan([_batch("p1", 1, install=B), _batch("p1", 2), _batch("p1", 5, install=A)]) == [
        None,
        1,
        None,
    ]
    rows = ledger.unsaved_rows()
    assert [(r["last_seq"], r["install_ms"]) for r in rows] == [(1, B)]
    ledger.saved(rows)
    assert ledger.unsaved_rows() == []


def test_installs_are_carried_across_a_restart() -> None:
    ledger = DeviceLedger("hq", {"p1": ("p1", None, 40, A)})  # SQL as of the last snapshot
    ledger.replayed(_batch("p1", 0, install=B))  # the log holds the reinstall
    ledger.replayed(_batch("p1", 1, install=B))
    assert ledger.plan([_batch("p1", 41, install=A), _batch("p1", 2, install=B)]) == [None, 1]
