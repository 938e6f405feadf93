"""A cluster worker (``CROWDSLAM_ROLE=worker``): it owns buildings through leases and tracks them exactly as
the embedded server does (``server.buildings``: the same tracker, batch log, snapshots and transactions).

- **Sharing out.** Every worker beats in a members bucket; each takes free buildings (``Leases.acquire``)
  up to its share, the number of buildings over the number of live workers, rounded up, and gives up one
  building per round while it holds more (a worker that joins gets buildings this way).
- **Keeping.** Leases are rewritten every third of their TTL. A lease found taken, or not rewritten for
  most of its TTL (NATS unreachable: it may have expired), is lost: the building is dropped at once
  without a snapshot (another worker may own it and write its state now).
- **Taking over.** A building is opened from its SQL snapshot and batch log (``BuildingHost``), then its
  subject in the batch stream is read in order from the sequence after the last one committed
  (``repositories.stream_position``): batches another worker had received but not committed are applied
  here, and their receipts go to the fronts still waiting for them.
- **Applying.** Batches join the building's queue in stream order; each group's transaction stores the
  group's last sequence (the acknowledgement: JetStream's own acks would come after the commit and could
  be lost with the worker). A group that finds the stored sequence ahead of its own was applied by another
  worker meanwhile: this worker lost the building and drops it.
- **Handing off.** A building given up (rebalance, shutdown) stops reading, finishes what it read, is
  snapshotted, and only then is its lease released: the next owner starts from the snapshot.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import faulthandler
import io
import logging
import math
import os
import signal
import socket
import time
import uuid
from collections.abc import Coroutine
from dataclasses import dataclass, field
from typing import Any

from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.aio.subscription import Subscription
from sqlalchemy.orm import Session, sessionmaker

from server.buildings.handles import BuildingThread
from server.buildings.registry import TrackingService
from server.buildings.submissions import received_batch
from server.cluster import messages
from server.cluster.batch_stream import BatchStream, StreamedBatch
from server.cluster.connection import connect
from server.cluster.leases import Lease, LeaseLostError, Leases
from server.cluster.live_relay import LiveRelay
from server.cluster.members import Members
from server.cluster.names import calls_subject
from server.errors import NotFoundError, ProblemError
from server.live.broadcast import Broadcaster
from server.settings import Settings
from server.slam.config import load_calibration, tracker_params
from server.slam.warmup import warm_kernels
from server.store import repositories as repo
from server.store.db import make_engine, make_session_factory
from server.store.migrate import current_revision, head_revision
from server.store.vacuum import vacuum_in_background

logger = logging.getLogger(__name__)

BALANCE_PERIOD_S = 1.0
"""How often a worker looks for free buildings (a killed worker's buildings are free once its leases
expire: the takeover starts within this time after)."""
MAX_IN_FLIGHT = 1024
"""Batches of a building read from the stream and not yet answered; reading waits beyond."""
RESUME_AFTER_S = 1.0
HAND_OFF_TIMEOUT_S = 60.0


@dataclass
class Owned:
    """A building this worker holds."""

    lease: Lease
    refreshed: float
    worker: BuildingThread | None = None
    consumer: asyncio.Task[None] | None = None
    calls: Subscription | None = None
    in_flight: set[asyncio.Task[None]] = field(default_factory=set)
    window: asyncio.Semaphore = field(default_factory=lambda: asyncio.Semaphore(MAX_IN_FLIGHT))
    last_read: int = 0
    """The last stream sequence queued to the building: reading resumes after it (a NATS outage)."""
    created: str = ""
    """When the building's row was created: batches posted to an earlier building of the same id (a
    database made anew under an old stream) are not its own."""
    foreign: int = 0
    lease_turn: asyncio.Lock = field(default_factory=asyncio.Lock)
    gone: bool = False


class ClusterWorker:
    def __init__(
        self,
        connection: Client,
        stream: BatchStream,
        leases: Leases,
        members: Members,
        tracking: TrackingService,
        sessions: sessionmaker[Session],
        ttl_s: float,
    ) -> None:
        self.connection = connection
        self.js = connection.jetstream()
        self.stream = stream
        self.leases = leases
        self.members = members
        self.tracking = tracking
        self.sessions = sessions
        self.ttl_s = ttl_s
        self.owned: dict[str, Owned] = {}
        self._turn = asyncio.Lock()  # takes, hand-offs and losses, one at a time
        self._background: set[asyncio.Task[None]] = set()

    @property
    def worker_id(self) -> str:
        return self.leases.owner

    async def run(self, stop: asyncio.Event) -> None:
        """Share the buildings out with the other workers until ``stop``; then hand every building off."""
        await self.members.heartbeat()
        beating = asyncio.get_running_loop().create_task(self._beat_forever())
        try:
            while not stop.is_set():
                try:
                    await self._balance()
                except Exception:
                    logger.exception(
                        "worker %s: sharing the buildings out failed; trying again", self.worker_id
                    )
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), BALANCE_PERIOD_S)
        finally:
            logger.info("worker %s: stopping; handing %d buildings off", self.worker_id, len(self.owned))
            for building_id in list(self.owned):
                try:
                    await asyncio.wait_for(self._hand_off(building_id), HAND_OFF_TIMEOUT_S)
                except TimeoutError:  # its lease expires: the next owner replays the batch log
                    logger.error("worker %s: handing %s off timed out", self.worker_id, building_id)
            beating.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await beating
            with contextlib.suppress(Exception):
                await self.members.leave()

    # ------------------------------------------------------------------ sharing out
    async def _balance(self) -> None:
        buildings = await asyncio.to_thread(self._building_ids)
        workers = await self.members.live() | {self.worker_id}
        share = math.ceil(len(buildings) / len(workers))
        if len(self.owned) > share:
            newest = next(reversed(self.owned))
            logger.info("worker %s: handing %s off (%d workers)", self.worker_id, newest, len(workers))
            await self._hand_off(newest)
            return
        free = [b for b in buildings if b not in self.owned]
        # workers try the free buildings in different orders
        free.sort(key=lambda b: hash((self.worker_id, b)))
        for building_id in free:
            if len(self.owned) >= share:
                break
            lease = await self.leases.acquire(building_id)
            if lease is not None:
                await self._take(building_id, lease)

    def _building_ids(self) -> list[str]:
        with self.sessions() as session:
            return [b.id for b in repo.list_buildings(session)]

    async def _beat_forever(self) -> None:
        period = self.ttl_s / 3
        while True:
            started = time.monotonic()
            try:
                await self.members.heartbeat()
            except Exception as exc:
                logger.warning("worker %s: heartbeat failed (%r)", self.worker_id, exc)
            for building_id, owned in list(self.owned.items()):
                await self._refresh(building_id, owned)
            await asyncio.sleep(max(0.0, period - (time.monotonic() - started)))

    async def _refresh(self, building_id: str, owned: Owned) -> None:
        try:
            async with owned.lease_turn:
                if owned.gone:
                    return
                owned.lease = await self.leases.refresh(owned.lease)
                owned.refreshed = time.monotonic()
        except LeaseLostError:
            self._in_background(self._lose(building_id, "its lease was taken or expired"))
        except Exception as exc:
            if time.monotonic() - owned.refreshed > 0.8 * self.ttl_s:
                self._in_background(self._lose(building_id, f"its lease could not be refreshed ({exc!r})"))

    def _in_background(self, work: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(work)
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    # ------------------------------------------------------------------ one building
    async def _take(self, building_id: str, lease: Lease) -> None:
        async with self._turn:
            owned = self.owned[building_id] = Owned(lease, time.monotonic())
            try:
                started = time.perf_counter()
                worker = await self.tracking.handle(building_id)  # its snapshot and batch log, from SQL
                assert isinstance(worker, BuildingThread)  # a worker tracks on threads of its own process
                owned.worker = worker
                owned.last_read, owned.created = await asyncio.to_thread(self._stream_position, building_id)

                async def call(msg: Msg) -> None:
                    await self._call(building_id, msg)

                owned.calls = await self.connection.subscribe(calls_subject(building_id), cb=call)
                owned.consumer = asyncio.get_running_loop().create_task(self._consume(building_id, owned))
                logger.info(
                    "worker %s: took building %s in %.2f s (replayed %d logged batches); reading its "
                    "batches after sequence %d",
                    self.worker_id,
                    building_id,
                    time.perf_counter() - started,
                    worker.counters.replayed,
                    owned.last_read,
                )
            except Exception as exc:
                if not isinstance(exc, NotFoundError):
                    logger.exception("worker %s: could not take building %s", self.worker_id, building_id)
                self.owned.pop(building_id, None)
                owned.gone = True
                await self._stop_reading(owned)
                await self.tracking.unload(building_id, snapshot=False)
                await self.leases.release(owned.lease)

    def _stream_position(self, building_id: str) -> tuple[int, str]:
        """The last stream sequence the building committed, and when its row was created."""
        with self.sessions() as session:
            row = repo.get_building(session, building_id)
            if row is None:
                raise NotFoundError(f"no building {building_id!r}")
            return repo.stream_position(session, building_id), row.created_at.isoformat()

    async def _hand_off(self, building_id: str) -> None:
        """Give the building up cleanly: stop reading, finish what was read, snapshot, release the lease."""
        async with self._turn:
            owned = self.owned.get(building_id)
            if owned is None:
                return
            await self._stop_reading(owned)
            if owned.in_flight:
                await asyncio.gather(*owned.in_flight, return_exceptions=True)
            self.owned.pop(building_id, None)
            try:
                await self.tracking.unload(building_id, snapshot=True)
            except Exception:
                logger.exception(
                    "worker %s: the snapshot of %s failed at hand-off", self.worker_id, building_id
                )
            async with owned.lease_turn:
                owned.gone = True
                with contextlib.suppress(Exception):
                    await self.leases.release(owned.lease)
            logger.info("worker %s: handed %s off", self.worker_id, building_id)

    async def _lose(self, building_id: str, why: str) -> None:
        """Drop a building that may be another worker's now: nothing more is written or answered for it."""
        async with self._turn:
            owned = self.owned.pop(building_id, None)
            if owned is None:
                return
            logger.warning("worker %s: lost building %s: %s", self.worker_id, building_id, why)
            owned.gone = True
            await self._stop_reading(owned)
            await self.tracking.unload(building_id, snapshot=False)
            for task in owned.in_flight:
                task.cancel()

    async def _stop_reading(self, owned: Owned) -> None:
        if owned.calls is not None:
            with contextlib.suppress(Exception):
                await owned.calls.unsubscribe()
        if owned.consumer is not None:
            owned.consumer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await owned.consumer

    # ------------------------------------------------------------------ batches and calls
    async def _consume(self, building_id: str, owned: Owned) -> None:
        while True:
            try:
                async for item in self.stream.read(self.js, building_id, owned.last_read):
                    await owned.window.acquire()
                    owned.last_read = item.sequence
                    self._queue(building_id, owned, item)
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                logger.warning(
                    "worker %s: reading %s's batches stopped (%r); resuming after sequence %d",
                    self.worker_id,
                    building_id,
                    exc,
                    owned.last_read,
                )
                await asyncio.sleep(RESUME_AFTER_S)

    def _queue(self, building_id: str, owned: Owned, item: StreamedBatch) -> None:
        assert owned.worker is not None
        try:
            reply_to, created, fields = messages.decode_stream_batch(item.body)
        except Exception:
            logger.exception(
                "worker %s: message %d of %s is unreadable", self.worker_id, item.sequence, building_id
            )
            owned.window.release()
            return
        if created != owned.created:
            owned.foreign += 1
            if owned.foreign == 1:
                logger.warning(
                    "worker %s: skipping batches posted to an earlier building %s (created %s, this one %s): "
                    "the stream outlived its database",
                    self.worker_id,
                    building_id,
                    created,
                    owned.created,
                )
            owned.window.release()
            return
        try:
            submission = dataclasses.replace(received_batch(*fields), stream_sequence=item.sequence)
        except ProblemError as exc:
            # what the building's decoding refuses, answered as the embedded server does
            owned.window.release()
            self._in_background(self.connection.publish(reply_to, messages.encode_answer(exc)))
            return
        future = owned.worker.enqueue(submission)
        task = asyncio.get_running_loop().create_task(self._answer(building_id, owned, future, reply_to))
        owned.in_flight.add(task)
        task.add_done_callback(owned.in_flight.discard)

    async def _answer(
        self, building_id: str, owned: Owned, future: asyncio.Future[bytes], reply_to: str
    ) -> None:
        value: bytes | Exception
        try:
            value = await future
        except repo.StaleStreamPositionError:
            self._in_background(self._lose(building_id, "another worker applied its batches"))
            return
        except Exception as exc:
            value = exc
        finally:
            owned.window.release()
        if owned.gone:
            return  # the building's next owner applies the batch again and answers
        await self.connection.publish(reply_to, messages.encode_answer(value))

    async def _call(self, building_id: str, msg: Msg) -> None:
        owned = self.owned.get(building_id)
        if owned is None or owned.worker is None or owned.gone:
            return  # not this worker's any more: the front times out and the operator retries
        value: object
        try:
            value = await owned.worker.ask(messages.decode_call(msg.data))
        except Exception as exc:
            value = exc
        await msg.respond(messages.encode_answer(value))


def log_tasks() -> None:
    """SIGUSR1: log where every task of the worker waits (a worker that does not stop says why)."""
    for task in asyncio.all_tasks():
        stream = io.StringIO()
        task.print_stack(file=stream)
        logger.warning("task %s:\n%s", task.get_name(), stream.getvalue())
    faulthandler.dump_traceback(all_threads=True)


async def serve(settings: Settings) -> None:
    """The worker role, until SIGTERM or SIGINT (then every building is handed off)."""
    problem = settings.cluster_problem()
    if problem is not None:
        raise SystemExit(problem)
    assert settings.nats_url is not None
    engine = make_engine(settings.resolved_database_url)
    try:
        current, head = current_revision(engine), head_revision(engine)
        if current != head:
            raise SystemExit(
                f"the database is at revision {current!r}, the worker needs {head!r}: run `crowdslam migrate`"
            )
        vacuum_in_background(engine)  # PostgreSQL without autovacuum; stops with engine.dispose()
        warm_kernels(tracker_params(settings), load_calibration(settings.encounter_calibration))
        worker_id = f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        connection = await connect(settings.nats_url, f"crowdslam-worker-{worker_id}")
        try:
            js = connection.jetstream()
            stream = BatchStream()
            await stream.ensure(js, settings.stream_retention_s)
            leases = await Leases.open(js, worker_id, settings.lease_ttl_s)
            members = await Members.open(js, worker_id, settings.lease_ttl_s)
            broadcaster = Broadcaster()
            relay = LiveRelay(connection)
            broadcaster.add_sink(relay)
            sessions = make_session_factory(engine)
            # one numba thread a building: a worker is a process per core, its buildings its threads (numba's
            # pool had its workers spin between the back-to-back launches of several buildings)
            tracking = TrackingService(sessions, broadcaster, settings, in_processes=False, kernel_threads=1)
            worker = ClusterWorker(
                connection, stream, leases, members, tracking, sessions, settings.lease_ttl_s
            )
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, stop.set)
            loop.add_signal_handler(signal.SIGUSR1, log_tasks)
            logger.info("worker %s: serving buildings (lease TTL %g s)", worker_id, settings.lease_ttl_s)
            try:
                await worker.run(stop)
            finally:
                await tracking.close()
                await relay.flush()
        finally:
            with contextlib.suppress(Exception):
                await connection.drain()
    finally:
        engine.dispose()
