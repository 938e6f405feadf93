"""A building in a process of its own (``CROWDSLAM_BUILDING_PROCESSES``): its batch path runs under its own
GIL, beside the HTTP front's event loop, so a busy building and the front use two cores, and buildings one
each. The building process holds the same ``BuildingHost`` as a building on a thread of the front
(``server.buildings.handles.BuildingThread``); this module is both ends of the socket between them.

Each frame is an 8-byte length and a pickle:
- front -> building: ``("batch", id, raw body, received_ns, BatchHeader, packed UserBatch or None, landmarks'
  JSON or None)`` (the header and the packed batch as plain tuples), ``("call", id, Call)``
  (``server.buildings.calls``), ``("close", id)``. The front converts every batch as far as it can without
  the building and sends it packed (``server.ingestion.transport``): a batch's landmarks (a phone's first
  fix) go apart as their JSON, which the building places in its frame (a building decodes the raw body
  only of a front that sends no packed batch);
- building -> front: first ``("ready", geo)`` or ``("failed", NotFoundError or None)`` (None: an error of
  the server's, which the building's process logs); then per group of batches
  ``("group", [(id, receipt JSON | ProblemError)], live messages as JSON, counters, seconds)``, and per call
  ``("result", id, ok, value or error)``.

Batches and calls are served in the order they arrive. The building process dies with the front (Linux:
``PR_SET_PDEATHSIG``; elsewhere when the socket closes): a crash of either is a crash of both, and the next
start restores the building from its snapshot and batch log. A building process that dies alone fails its
waiting requests with 503, and the next request starts it again the same way.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import multiprocessing
import os
import pickle
import select
import socket
import struct
import time
from typing import Any, TypeVar

import numba

from schemas.live import LiveMessage
from server.buildings.calls import Call
from server.buildings.counters import Counters
from server.buildings.groups import MAX_GROUP, GroupRunner
from server.buildings.handles import LatencyWindow
from server.buildings.host import IDLE_S, BuildingHost, open_building
from server.buildings.submissions import BatchFields, Submission, batch_fields, received_batch, transportable
from server.errors import NotFoundError, ProblemError, ServiceUnavailableError
from server.gc_tuning import tune_gc_for_serving
from server.live.broadcast import Broadcaster
from server.process_lifetime import die_with, interrupts_held
from server.settings import Settings
from server.slam.warmup import warm_kernels_for
from slam_core.geo import GeoFrame

_HEADER = struct.Struct("!Q")
T = TypeVar("T")


class BuildingLoadError(RuntimeError):
    """A building's process could not load its building (its process logged why)."""

    def __init__(self, building_id: str) -> None:
        super().__init__(f"building {building_id!r}: its process could not load it")


START_TIMEOUT_S = 300.0
"""A first start compiles the numba kernels (about a minute); later ones load them from the cache."""
CLOSE_TIMEOUT_S = 120.0


# --------------------------------------------------------------------------------------------- framing
def _send(sock: socket.socket, message: object) -> None:
    sock.sendall(_frame(message))


class FrameReader:
    """Frames from a blocking socket, read in large chunks: one ``recv`` brings every frame the front has
    sent since the last (reading each frame's header and body apart, with a ``select`` between frames, had
    cost three system calls a batch)."""

    CHUNK = 1 << 20

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._buffer = bytearray()
        self._offset = 0
        self._closed = False

    def next(self) -> Any | None:
        """The next frame, waiting for it; None when the other end has gone."""
        while True:
            frame = self._buffered()
            if frame is not _NONE:
                return frame
            if self._read(None) is None:
                return None

    def ready(self, timeout_s: float = 0.0) -> Any | None:
        """The next frame if one has arrived (buffered, or waiting in the socket) or arrives within
        ``timeout_s``, else ``_NONE``; None when the other end has gone."""
        deadline = time.monotonic() + timeout_s
        while True:
            frame = self._buffered()
            if frame is not _NONE:
                return frame
            got = self._read(max(0.0, deadline - time.monotonic()))
            if got is None:
                return None
            if not got:
                return _NONE

    def pending(self) -> bool:
        """Whether a frame, or part of one, has arrived and not been taken."""
        return len(self._buffer) > self._offset or bool(select.select([self.sock], [], [], 0)[0])

    def _buffered(self) -> Any:
        start = self._offset + _HEADER.size
        if len(self._buffer) < start:
            return _NONE
        end = start + _HEADER.unpack_from(self._buffer, self._offset)[0]
        if len(self._buffer) < end:
            return _NONE
        self._offset = end
        return pickle.loads(self._buffer[start:end])

    def _read(self, timeout_s: float | None) -> bool | None:
        """Append what the socket holds once it holds something (``timeout_s``: waiting that long at most,
        None: for as long as it takes): whether anything came; None when the other end has gone."""
        if self._closed:
            return None
        if timeout_s is not None and not select.select([self.sock], [], [], timeout_s)[0]:
            return False
        chunk = self.sock.recv(self.CHUNK)
        if not chunk:
            self._closed = True
            return None
        del self._buffer[: self._offset]
        self._offset = 0
        self._buffer += chunk
        return True


_NONE: Any = object()
"""``FrameReader``'s "no complete frame yet" (a frame itself is never this object)."""


async def _read_frame(reader: asyncio.StreamReader) -> Any | None:
    try:
        header = await reader.readexactly(_HEADER.size)
        return pickle.loads(await reader.readexactly(_HEADER.unpack(header)[0]))
    except (asyncio.IncompleteReadError, ConnectionError):
        return None


def _frame(message: object) -> bytes:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    return _HEADER.pack(len(data)) + data


# ------------------------------------------------------------------------------------ building side
def serve_building(building_id: str, settings: Settings, sock: socket.socket, front_pid: int) -> None:
    """Entry point of a building's process: load the building, then serve the front until it closes."""
    die_with(front_pid)
    # One core per building: its batch kernels run on its own thread. With numba's thread pool, OpenMP's
    # workers spun between the back-to-back launches (half a core), or, told to sleep, took a wake-up per
    # launch.

    numba.set_num_threads(1)
    # kernels warm and the GC tuned before the first batch, as the front's lifespan does for its own
    warm_kernels_for(settings)
    tune_gc_for_serving()
    try:
        building = open_building(settings, building_id)
    except Exception as exc:
        # a building that does not exist is the caller's to hear of; any other error is the server's: told
        # as such, its traceback left to this process's log
        _send(sock, ("failed", exc if isinstance(exc, NotFoundError) else None))
        raise
    _send(sock, ("ready", building.geo))
    _BuildingLoop(building, sock).run()


class _BuildingLoop:
    def __init__(self, host: BuildingHost, sock: socket.socket) -> None:
        self.host = host
        self.sock = sock
        self.batches: list[tuple[int, BatchFields]] = []
        self.reader = FrameReader(sock)
        self.groups = GroupRunner(host)

    def run(self) -> None:
        reader = self.reader
        while True:
            frame = reader.ready(IDLE_S)
            if frame is None:  # the front is gone without closing us: a crash, nothing more to write
                return
            if frame is _NONE:
                self.host.idle()
                continue
            frames = [frame]
            now = time.monotonic()
            deadline = now + self.groups.wait_s() if frame[0] == "batch" else now
            while len(self.batches) + len(frames) < MAX_GROUP:
                more = reader.ready(max(0.0, deadline - time.monotonic()))
                if more is None:
                    return
                if more is _NONE:
                    break
                frames.append(more)
                if more[0] != "batch":  # a call waits: no more lingering
                    deadline = 0.0
            for f in frames:
                if f[0] == "batch":
                    self.batches.append((f[1], f[2:]))
                    continue
                self._flush()
                if f[0] == "close":
                    self.host.close()
                    if self.host.recorder is not None:
                        self.host.recorder.close()
                    _send(self.sock, ("result", f[1], True, None))
                    return
                self._call(f[1], f[2])
            self._flush()

    def _flush(self) -> None:
        if not self.batches:
            return
        ids: list[int] = []
        group: list[Submission] = []
        answers: dict[int, bytes | Exception] = {}
        for request, fields in self.batches:
            try:
                submission = received_batch(*fields)
            except ProblemError as exc:
                answers[request] = exc
                continue
            ids.append(request)
            group.append(submission)
        self.batches = []
        texts: list[str] = []
        seconds = 0.0
        if group:
            done = self.groups.run(group, self.reader.pending)
            wire = (a if isinstance(a, bytes) else transportable(a) for a in done.answers)
            answers.update(zip(ids, wire, strict=True))
            texts, seconds = done.texts, done.seconds
        _send(self.sock, ("group", list(answers.items()), texts, self.host.counters, seconds))

    def _call(self, request: int, call: Call[Any]) -> None:
        try:
            if not isinstance(call, Call):
                raise TypeError(f"not a building call: {type(call).__name__}")
            value = call.run(self.host)
        except Exception as exc:
            _send(self.sock, ("result", request, False, transportable(exc)))
            return
        _send(self.sock, ("result", request, True, value))


# -------------------------------------------------------------------------------------- front side
def _start(process: Any) -> None:
    with interrupts_held():  # Ctrl-C is the front's to handle: it closes its buildings in order
        process.start()


class BuildingProcess:
    """The front's handle on a building process, with ``BuildingThread``'s interface."""

    def __init__(
        self,
        building_id: str,
        process: Any,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        geo: GeoFrame | None,
        broadcaster: Broadcaster,
    ) -> None:
        self.building_id = building_id
        self._process = process
        self._reader, self._writer = reader, writer
        self._geo = geo
        self._broadcaster = broadcaster
        self._ids = itertools.count()
        self._waiting: dict[int, asyncio.Future[Any]] = {}
        self._outbox: list[bytes] = []
        self.counters = Counters()
        self.latency = LatencyWindow()
        self.group_sizes = LatencyWindow()
        self.alive = True
        self._listening = asyncio.get_running_loop().create_task(self._listen())

    @classmethod
    async def start(cls, building_id: str, settings: Settings, broadcaster: Broadcaster) -> BuildingProcess:
        front, back = socket.socketpair()
        context = multiprocessing.get_context("spawn")
        process = context.Process(
            target=serve_building,
            args=(building_id, settings, back, os.getpid()),
            name=f"crowdslam-building-{building_id}",
            daemon=True,
        )
        await asyncio.to_thread(_start, process)
        back.close()
        reader, writer = await asyncio.open_unix_connection(sock=front)
        try:
            first = await asyncio.wait_for(_read_frame(reader), timeout=START_TIMEOUT_S)
        except TimeoutError:
            first = None
        if first is None or first[0] != "ready":
            writer.close()
            await asyncio.to_thread(process.join, 10.0)
            if process.is_alive():
                process.kill()
            if first is not None and isinstance(first[1], NotFoundError):
                raise first[1]
            raise BuildingLoadError(building_id)
        return cls(building_id, process, reader, writer, first[1], broadcaster)

    @property
    def pid(self) -> int | None:
        pid: int | None = self._process.pid
        return pid

    @property
    def geo(self) -> GeoFrame | None:
        return self._geo

    @property
    def queue_depth(self) -> int:
        return len(self._waiting)

    async def submit(self, submission: Submission) -> bytes:
        answer: bytes = await self._ask(("batch", *batch_fields(submission)))
        return answer

    async def ask(self, call: Call[T]) -> T:
        answer: T = await self._ask(("call", call))
        return answer

    def publish(self, messages: list[LiveMessage]) -> None:
        self._broadcaster.publish(self.building_id, messages)

    async def _ask(self, message: tuple[Any, ...]) -> Any:
        if not self.alive:
            raise ServiceUnavailableError(f"building {self.building_id!r} is restarting; send again")
        request = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._waiting[request] = future
        self._outbox.append(_frame((message[0], request, *message[1:])))
        if len(self._outbox) == 1:
            asyncio.get_running_loop().call_soon(self._send_outbox)
        return await future

    def _send_outbox(self) -> None:
        """The frames of one turn of the event loop in one write: under load the front reads many requests a
        turn, and a write each was a system call each (and a wake-up of the building when it waited)."""
        frames, self._outbox = self._outbox, []
        self._writer.write(b"".join(frames))

    async def _listen(self) -> None:
        while True:
            frame = await _read_frame(self._reader)
            if frame is None:
                break
            if frame[0] == "group":
                _, answers, texts, counters, seconds = frame
                self.counters = counters
                self.latency.add(seconds)
                self.group_sizes.add(len(answers))
                for request, answer in answers:
                    self._settle(request, answer, isinstance(answer, Exception))
                self._broadcaster.publish_texts(self.building_id, texts)
            elif frame[0] == "result":
                _, request, ok, value = frame
                self._settle(request, value, not ok)
        self.alive = False
        for future in self._waiting.values():
            if not future.done():
                future.set_exception(
                    ServiceUnavailableError(f"building {self.building_id!r} stopped; send again")
                )
        self._waiting.clear()

    def _settle(self, request: int, answer: Any, failed: bool) -> None:
        future = self._waiting.pop(request, None)
        if future is None or future.done():
            return
        if failed:
            future.set_exception(answer)
        else:
            future.set_result(answer)

    async def abandon(self) -> None:
        """Stop the building process without a snapshot."""
        self._process.kill()
        await self.close()

    async def close(self) -> None:
        """Snapshot and stop the building process (a clean shutdown leaves nothing to replay)."""
        if self.alive:
            with contextlib.suppress(ProblemError, TimeoutError):
                await asyncio.wait_for(self._ask(("close",)), timeout=CLOSE_TIMEOUT_S)
        self._writer.close()
        await asyncio.to_thread(self._process.join, 30.0)
        if self._process.is_alive():
            self._process.kill()
        self._listening.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._listening
