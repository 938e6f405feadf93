"""A building's handle: what the API submits batches and calls to, one building at a time.

``BuildingThread`` runs the building on a thread of this process: requests enqueue and await their receipt;
the building's task drains the queue into a group, runs it in the building's thread (numba kernels release
the GIL, SQL waits on I/O) and publishes the group's live messages. ``server.buildings.process`` runs the
same behind the same ``BuildingHandle`` protocol in a process of its own.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Protocol, TypeVar

import numba

from schemas.live import LiveMessage
from server.buildings.calls import Call
from server.buildings.counters import Counters
from server.buildings.groups import MAX_GROUP, GroupRunner
from server.buildings.host import IDLE_S, BuildingHost
from server.buildings.submissions import Submission
from server.errors import ServiceUnavailableError
from server.live.broadcast import Broadcaster
from slam_core.geo import GeoFrame

T = TypeVar("T")


class BuildingHandle(Protocol):
    """What the API sees of a building: ``BuildingThread`` (a thread of this process) or
    ``server.buildings.process.BuildingProcess`` (a process of its own)."""

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
    async def ask(self, call: Call[T]) -> T:
        """Run ``call`` on the building, in order with its batches."""
        ...

    def publish(self, messages: list[LiveMessage]) -> None: ...
    async def close(self) -> None: ...
    async def abandon(self) -> None: ...


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


class BuildingThread:
    def __init__(
        self, host: BuildingHost, broadcaster: Broadcaster, kernel_threads: int | None = None
    ) -> None:
        """``kernel_threads``: the numba threads the building's kernels may use (default: numba's, every
        core); a cluster worker gives each building one, as a building's process does."""
        self.host = host
        self._broadcaster = broadcaster
        self._queue: asyncio.Queue[_Pending] = asyncio.Queue()

        def limit_kernel_threads() -> None:
            if kernel_threads is not None:
                numba.set_num_threads(kernel_threads)

        self._executor = ThreadPoolExecutor(
            max_workers=1,
            thread_name_prefix=f"building-{host.building_id}",
            initializer=limit_kernel_threads,
        )
        self._task = asyncio.get_running_loop().create_task(self._run())
        self.latency = LatencyWindow()
        self.group_sizes = LatencyWindow()
        self._groups = GroupRunner(host)
        self.alive = True

    @property
    def queue_depth(self) -> int:
        return self._queue.qsize()

    @property
    def geo(self) -> GeoFrame | None:
        return self.host.geo

    @property
    def counters(self) -> Counters:
        return self.host.counters

    async def submit(self, submission: Submission) -> bytes:
        """The batch's receipt, as JSON."""
        return await self.enqueue(submission)

    def enqueue(self, submission: Submission) -> asyncio.Future[bytes]:
        """Queue the batch now (batches are applied in the order they are queued); its receipt's future."""
        future: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        self._queue.put_nowait(_Pending(submission, future))
        return future

    async def ask(self, call: Call[T]) -> T:
        """Run ``call`` on the building's thread (anchor edits stay ordered with batches)."""
        return await asyncio.get_running_loop().run_in_executor(self._executor, call.run, self.host)

    def publish(self, messages: list[LiveMessage]) -> None:
        self._broadcaster.publish(self.host.building_id, messages)

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            try:
                group = [await asyncio.wait_for(self._queue.get(), IDLE_S)]
            except TimeoutError:
                await loop.run_in_executor(self._executor, self.host.idle)
                continue
            try:
                wait = self._groups.wait_s()
                if wait > 0:
                    await asyncio.sleep(wait)
                while not self._queue.empty() and len(group) < MAX_GROUP:
                    group.append(self._queue.get_nowait())
                done = await loop.run_in_executor(
                    self._executor,
                    self._groups.run,
                    [p.submission for p in group],
                    lambda: not self._queue.empty(),
                )
            except asyncio.CancelledError:  # stopped: nobody waits for a group that may never be answered
                self._fail_stopped(group)
                raise
            self.latency.add(done.seconds)
            self.group_sizes.add(len(group))
            for p, answer in zip(group, done.answers, strict=True):
                if p.future.done():
                    continue
                if isinstance(answer, Exception):
                    p.future.set_exception(answer)
                else:
                    p.future.set_result(answer)
            self.publish(done.messages)

    async def close(self) -> None:
        # a clean stop leaves nothing to replay: the next start loads this snapshot and an empty log
        await self._stop(self.host.close)

    async def abandon(self) -> None:
        """Stop without a snapshot: the building is another worker's now (cluster mode)."""
        await self._stop(self.host.abandon)

    def _fail_stopped(self, pending: list[_Pending]) -> None:
        """Answer batches the stopped building will not apply: send them again (to its next owner)."""
        stopped = ServiceUnavailableError(f"building {self.host.building_id!r} stopped; send again", 1.0)
        for p in pending:
            if not p.future.done():
                p.future.set_exception(stopped)

    async def _stop(self, last: Callable[[], None]) -> None:
        self.alive = False
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        self._fail_stopped([self._queue.get_nowait() for _ in range(self._queue.qsize())])
        await asyncio.get_running_loop().run_in_executor(self._executor, last)
        self._executor.shutdown(wait=True)
        if self.host.recorder is not None:
            self.host.recorder.close()
