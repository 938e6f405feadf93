"""The asynchronous side of the batch path: one queue and one worker thread per building.

Requests enqueue and await their receipt; the building's task drains the queue into a group, runs it in the
building's thread (numba kernels release the GIL, SQL waits on I/O) and publishes the group's live messages.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from sqlalchemy.orm import Session, sessionmaker

from schemas.live import LiveMessage
from server.broadcast import Broadcaster
from server.errors import NotFoundError, ProblemError
from server.recording import BuildingRecorder
from server.session_types import Counters, Retention, Submission
from server.settings import Settings
from server.store import repositories as repo
from server.tracking import BuildingSession
from slam_core.encounters import Calibration
from slam_core.geo import GeoFrame
from slam_core.tracker import TrackerParams

MAX_GROUP = 256


CALLS = frozenset({"anchors", "get_anchor", "put_known_anchor", "delete_anchor", "merge_anchors", "context"})
"""The building session's methods the API may call (``BuildingWorker.call``), in order with its batches."""


class Worker(Protocol):
    """What the API sees of a building: ``BuildingWorker`` (a thread of this process) or
    ``server.building_process.ProcessBuildingWorker`` (a process of its own)."""

    alive: bool
    latency: LatencyWindow
    group_sizes: LatencyWindow

    @property
    def geo(self) -> GeoFrame | None: ...
    @property
    def counters(self) -> Counters: ...
    @property
    def queue_depth(self) -> int: ...
    async def submit(self, submission: Submission) -> bytes: ...
    async def call(self, name: str, *args: Any) -> Any: ...
    def publish(self, messages: list[LiveMessage]) -> None: ...
    async def close(self) -> None: ...


@dataclass
class _Pending:
    submission: Submission
    future: asyncio.Future[bytes]


@dataclass
class LatencyWindow:
    """The most recent processing latencies (seconds), for /metrics."""

    values: list[float] = field(default_factory=list)
    limit: int = 10_000

    def add(self, value: float) -> None:
        self.values.append(value)
        if len(self.values) > self.limit:
            del self.values[: len(self.values) - self.limit]


class BuildingWorker:
    def __init__(self, session: BuildingSession, broadcaster: Broadcaster) -> None:
        self.session = session
        self._broadcaster = broadcaster
        self._queue: asyncio.Queue[_Pending] = asyncio.Queue()
        self._executor = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix=f"building-{session.building_id}"
        )
        self._task = asyncio.get_running_loop().create_task(self._run())
        self.latency = LatencyWindow()
        self.group_sizes = LatencyWindow()
        self.alive = True

    @property
    def queue_depth(self) -> int:
        return self._queue.qsize()

    @property
    def geo(self) -> GeoFrame | None:
        return self.session.geo

    @property
    def counters(self) -> Counters:
        return self.session.counters

    async def submit(self, submission: Submission) -> bytes:
        """The batch's receipt, as JSON."""
        future: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        await self._queue.put(_Pending(submission, future))
        return await future

    async def call(self, name: str, *args: Any) -> Any:
        """Run one of the session's ``CALLS`` on the building's thread (anchor edits stay ordered with
        batches)."""
        if name not in CALLS:
            raise ValueError(f"unknown building call {name!r}; valid: {', '.join(sorted(CALLS))}")
        method = getattr(self.session, name)
        return await asyncio.get_running_loop().run_in_executor(self._executor, lambda: method(*args))

    def publish(self, messages: list[LiveMessage]) -> None:
        self._broadcaster.publish(self.session.building_id, messages)

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            group = [await self._queue.get()]
            while not self._queue.empty() and len(group) < MAX_GROUP:
                group.append(self._queue.get_nowait())
            started = time.perf_counter()
            try:
                receipts, messages = await loop.run_in_executor(
                    self._executor, self._process, [p.submission for p in group]
                )
            except Exception as exc:
                for p in group:
                    if not p.future.done():
                        p.future.set_exception(exc)
                continue
            self.latency.add(time.perf_counter() - started)
            self.group_sizes.add(len(group))
            for p, receipt in zip(group, receipts, strict=True):
                if p.future.done():
                    continue
                if isinstance(receipt, ProblemError):
                    p.future.set_exception(receipt)
                else:
                    p.future.set_result(receipt)
            self.publish(messages)

    def _process(self, group: list[Submission]) -> tuple[list[bytes | ProblemError], list[LiveMessage]]:
        """On the building's thread: the group, with its receipts serialised there."""
        result = self.session.process(group)
        receipts = [
            r if isinstance(r, ProblemError) else r.model_dump_json().encode() for r in result.receipts
        ]
        return receipts, result.messages

    async def close(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        # a clean stop leaves nothing to replay: the next start loads this snapshot and an empty log
        await asyncio.get_running_loop().run_in_executor(self._executor, self.session.close)
        self._executor.shutdown(wait=True)
        if self.session.recorder is not None:
            self.session.recorder.close()


class TrackingService:
    """The registry of buildings being tracked; a building is loaded on first use."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        broadcaster: Broadcaster,
        params: TrackerParams,
        calibration: Calibration,
        seed: int,
        recordings: Path | None = None,
        snapshot_period_s: float = 60.0,
        retention: Retention | None = None,
        processes: Settings | None = None,
    ) -> None:
        """``processes``: run each building in a process of its own, configured by these settings."""
        self._processes = processes
        self._snapshot_period_s = snapshot_period_s
        self._retention = retention
        self._recordings = recordings
        self._sessions = sessions
        self._broadcaster = broadcaster
        self._params = params
        self._calibration = calibration
        self._seed = seed
        self._workers: dict[str, Worker] = {}
        self._loading = asyncio.Lock()

    async def worker(self, building_id: str) -> Worker:
        worker = self._workers.get(building_id)
        if worker is not None and worker.alive:
            return worker
        async with self._loading:
            worker = self._workers.get(building_id)
            if worker is not None and not worker.alive:  # its process died: start it again
                await worker.close()
                worker = None
            if worker is None and self._processes is not None:
                from server.building_process import ProcessBuildingWorker  # it imports this module

                if not await asyncio.to_thread(self._exists, building_id):  # never a process for nothing
                    raise NotFoundError(f"no building {building_id!r}")
                worker = await ProcessBuildingWorker.start(building_id, self._processes, self._broadcaster)
                self._workers[building_id] = worker
            elif worker is None:
                recorder = (
                    None if self._recordings is None else BuildingRecorder(self._recordings, building_id)
                )
                session = await asyncio.to_thread(
                    BuildingSession,
                    building_id,
                    self._sessions,
                    self._params,
                    self._calibration,
                    self._seed,
                    recorder,
                    self._snapshot_period_s,
                    self._retention,
                )
                worker = self._workers[building_id] = BuildingWorker(session, self._broadcaster)
        return worker

    def _exists(self, building_id: str) -> bool:
        with self._sessions() as session:
            return repo.get_building(session, building_id) is not None

    @property
    def workers(self) -> dict[str, Worker]:
        return dict(self._workers)

    async def close(self) -> None:
        for worker in self._workers.values():
            await worker.close()
        self._workers.clear()
