"""A busy building gathers the batches that arrive while it works into its next group (``GroupPacing``):
a crowd's batches share groups (one a linger instead of one a batch), while a phone posting alone, or a
replay posting each batch after the last one's receipt, never waits; in a building's thread
(``BuildingThread``) and in a building's process (``_BuildingLoop``) alike."""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from server.buildings import process as building_process
from server.buildings.groups import GroupPacing
from server.buildings.handles import BuildingThread
from server.buildings.process import _BuildingLoop, _frame
from server.buildings.submissions import GroupResult
from server.live.broadcast import Broadcaster


def test_the_next_group_waits_only_while_the_building_is_busy() -> None:
    pacing = GroupPacing(0.02)
    assert pacing.wait_s(100.0) == 0.0  # nothing yet
    pacing.start(100.0)
    pacing.end(1, waiting=False)  # alone, and nothing came meanwhile
    assert pacing.wait_s(100.005) == 0.0
    pacing.start(100.01)
    pacing.end(3, waiting=False)  # a group of three: busy
    assert pacing.wait_s(100.015) == pytest.approx(0.015)
    assert pacing.wait_s(100.05) == 0.0  # a group that took longer than the linger: the next starts at once
    pacing.start(100.05)
    pacing.end(1, waiting=True)  # one, with batches waiting behind it: busy
    assert pacing.wait_s(100.06) == pytest.approx(0.01)
    off = GroupPacing(0.0)
    off.start(1.0)
    off.end(50, waiting=True)
    assert off.wait_s(1.0) == 0.0


class _Receipt:
    def model_dump_json(self) -> str:
        return "{}"


@dataclass
class _Building:
    """What a worker needs of a building; each group takes ``work_s`` and is remembered by its size."""

    group_linger_s: float
    work_s: float = 0.002
    building_id: str = "hq"
    recorder: Any = None
    counters: Any = None
    groups: list[int] = field(default_factory=list)

    def process(self, group: list[Any]) -> GroupResult:
        time.sleep(self.work_s)
        self.groups.append(len(group))
        return GroupResult([_Receipt() for _ in group])  # type: ignore[misc]

    def close(self) -> None:
        pass


async def _crowd(worker: BuildingThread, batches: int, every_s: float) -> list[float]:
    """A batch every ``every_s`` on average, at random as a crowd's phones post, each awaited apart; the
    seconds each waited for its receipt."""
    gaps = np.random.default_rng(0).exponential(every_s, batches)

    async def one() -> float:
        started = time.monotonic()
        await worker.submit(object())  # type: ignore[arg-type]
        return time.monotonic() - started

    tasks = []
    for gap in gaps:
        tasks.append(asyncio.create_task(one()))
        await asyncio.sleep(gap)
    return list(await asyncio.gather(*tasks))


@pytest.mark.parametrize("linger_s", [0.0, 0.1])
def test_a_crowd_shares_groups_and_waits_no_longer_than_the_linger(linger_s: float) -> None:
    async def main() -> tuple[list[int], list[float]]:
        building = _Building(linger_s)
        worker = BuildingThread(building, Broadcaster())  # type: ignore[arg-type]
        waits = await _crowd(worker, 120, 0.005)  # 200 batches a second, 2 ms a group
        await worker.close()
        return building.groups, waits

    groups, waits = asyncio.run(main())
    assert sum(groups) == 120
    if linger_s:
        assert len(groups) <= 30, groups  # ~0.6 s of batches: about one group a linger
        assert max(waits) < linger_s + 0.25
    else:
        assert len(groups) >= 60, groups  # each batch alone, or nearly


def test_a_phone_posting_alone_never_waits() -> None:
    async def main() -> tuple[list[int], float]:
        building = _Building(0.5)
        worker = BuildingThread(building, Broadcaster())  # type: ignore[arg-type]
        started = time.monotonic()
        for _ in range(20):  # each after the last one's receipt, as a replay posts
            await worker.submit(object())  # type: ignore[arg-type]
        took = time.monotonic() - started
        await worker.close()
        return building.groups, took

    groups, took = asyncio.run(main())
    assert groups == [1] * 20
    assert took < 0.5  # twenty lingers would be 10 s


def test_a_building_process_gathers_a_crowd_and_answers_a_lone_phone_at_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(building_process, "received_batch", lambda *fields: fields)
    front, side = socket.socketpair()
    front.settimeout(10.0)  # a loop that died answers nothing: fail, do not hang
    building = _Building(0.1)
    loop = _BuildingLoop(building, side)  # type: ignore[arg-type]
    runner = threading.Thread(target=loop.run)
    runner.start()
    answers = building_process.FrameReader(front)

    def receipts(n: int) -> None:
        got = 0
        while got < n:
            frame = answers.next()
            assert frame is not None
            assert frame[0] == "group"
            got += len(frame[1])

    started = time.monotonic()
    for k in range(5):  # alone: each answered before the next is sent
        front.sendall(_frame(("batch", k, b"", 0, (), None)))
        receipts(1)
    assert time.monotonic() - started < 0.4  # five lingers would be 0.5 s
    assert building.groups == [1] * 5

    def crowd() -> None:
        for k, gap in enumerate(np.random.default_rng(0).exponential(0.005, 120)):
            front.sendall(_frame(("batch", 100 + k, b"", 0, (), None)))
            time.sleep(gap)

    sender = threading.Thread(target=crowd)
    sender.start()
    receipts(120)
    sender.join()
    front.sendall(_frame(("close", 1)))
    assert answers.next() == ("result", 1, True, None)
    runner.join(5.0)
    front.close()
    side.close()
    crowd_groups = building.groups[5:]
    assert sum(crowd_groups) == 120
    assert len(crowd_groups) <= 30, crowd_groups
