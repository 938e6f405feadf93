"""A cluster front's view of the buildings (``CROWDSLAM_ROLE=front``): each building is tracked by whichever
worker holds its lease, somewhere else. A batch the front accepted goes to the batch stream with the
subject its receipt is to come back on; the front waits for that receipt, and answers 503 with Retry-After
when it does not come in time (a worker died and another is taking the building over): the phone's retry is
safe, the worker's batch log answers ``duplicate`` for a batch applied meanwhile. Operators' calls go to the
building's worker as NATS requests. Live messages of every building come from the workers over NATS and go
to this front's dashboards."""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
import uuid
from typing import Any, TypeVar

from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.aio.subscription import Subscription
from nats.errors import Error as NatsError
from nats.errors import NoRespondersError
from nats.errors import TimeoutError as NatsTimeoutError
from sqlalchemy.orm import Session, sessionmaker

from schemas.live import LiveMessage
from server.buildings.calls import Call
from server.buildings.counters import Counters
from server.buildings.handles import BuildingHandle, LatencyWindow
from server.buildings.recovery import building_geo
from server.buildings.registry import LoadFailure
from server.buildings.submissions import Submission, batch_fields
from server.cluster import messages
from server.cluster.batch_stream import BatchStream
from server.cluster.live_relay import LiveRelay
from server.cluster.names import (
    LIVE_SUBJECTS,
    calls_subject,
    receipts_subject,
    token_building,
)
from server.errors import NotFoundError, ServiceUnavailableError
from server.live.broadcast import Broadcaster
from server.store import repositories as repo
from slam_core.geo import GeoFrame

logger = logging.getLogger(__name__)

T = TypeVar("T")

RETRY_AFTER_S = 2.0
"""What a 503 tells the phone to wait: about the time a worker takes to open a building it took over."""
NO_OWNER_POLL_S = 0.25
KNOWN_FOR_S = 10.0
"""How long the front trusts that a building exists (and its geo-reference) before asking SQL again."""


class ClusterBuildings:
    """The ``Buildings`` of a front: a ``RemoteBuilding`` per building asked for."""

    def __init__(
        self,
        connection: Client,
        stream: BatchStream,
        sessions: sessionmaker[Session],
        broadcaster: Broadcaster,
        timeout_s: float,
    ) -> None:
        self.connection = connection
        self.js = connection.jetstream()
        self.stream = stream
        self.front_id = uuid.uuid4().hex[:16]
        self.timeout_s = timeout_s
        self._sessions = sessions
        self._broadcaster = broadcaster
        self._buildings: dict[str, RemoteBuilding] = {}
        self._checked: dict[str, float] = {}
        self._requests = itertools.count()
        self.waiting: dict[int, asyncio.Future[bytes]] = {}
        self._subscriptions: list[Subscription] = []
        self.relay = LiveRelay(connection)

    @classmethod
    async def start(
        cls,
        connection: Client,
        stream: BatchStream,
        sessions: sessionmaker[Session],
        broadcaster: Broadcaster,
        timeout_s: float,
        retention_s: float,
    ) -> ClusterBuildings:
        front = cls(connection, stream, sessions, broadcaster, timeout_s)
        await stream.ensure(front.js, retention_s)
        front._subscriptions = [
            await connection.subscribe(receipts_subject(front.front_id), cb=front._on_receipt),
            await connection.subscribe(LIVE_SUBJECTS, cb=front._on_live),
        ]
        return front

    async def handle(self, building_id: str) -> BuildingHandle:
        building = self._buildings.get(building_id)
        checked = self._checked.get(building_id, -KNOWN_FOR_S)
        if building is None or time.monotonic() - checked > KNOWN_FOR_S:
            row = await asyncio.to_thread(self._building_row, building_id)
            if row is None:
                self._buildings.pop(building_id, None)
                raise NotFoundError(f"no building {building_id!r}")
            geo = building_geo(row)
            if building is None:
                building = self._buildings[building_id] = RemoteBuilding(self, building_id, geo)
            building.geo = geo
            building.created = row.created_at.isoformat()
            self._checked[building_id] = time.monotonic()
        return building

    def _building_row(self, building_id: str) -> Any:
        with self._sessions() as session:
            return repo.get_building(session, building_id)

    @property
    def handles(self) -> dict[str, BuildingHandle]:
        return dict(self._buildings)

    @property
    def load_failures(self) -> dict[str, LoadFailure]:
        """None known here: a worker that cannot load a building logs it and leaves the building to another
        (its phones hear 503 from the front until one can)."""
        return {}

    def request(self) -> tuple[int, str, asyncio.Future[bytes]]:
        """A new request's id, the subject its receipt comes back on, and the receipt's future."""
        request = next(self._requests)
        future: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        self.waiting[request] = future
        return request, receipts_subject(self.front_id, request), future

    async def _on_receipt(self, msg: Msg) -> None:
        try:
            request = int(msg.subject.rsplit(".", 1)[1])
        except ValueError:
            return
        future = self.waiting.pop(request, None)
        if future is None or future.done():
            return  # answered already (a receipt sent again by the worker that took the building over)
        try:
            future.set_result(messages.decode_answer(msg.data))
        except Exception as exc:
            future.set_exception(exc)

    async def _on_live(self, msg: Msg) -> None:
        try:
            building_id = token_building(msg.subject.rsplit(".", 1)[1])
        except ValueError:
            return
        self._broadcaster.publish_texts(building_id, messages.decode_live(msg.data))

    async def close(self) -> None:
        await self.relay.flush()
        for subscription in self._subscriptions:
            await subscription.unsubscribe()
        for future in self.waiting.values():
            if not future.done():
                future.set_exception(ServiceUnavailableError("the front is stopping", RETRY_AFTER_S))
        self.waiting.clear()


class RemoteBuilding:
    """A building as a front sees it, a ``BuildingHandle``; its tracking figures are on its worker's."""

    def __init__(self, front: ClusterBuildings, building_id: str, geo: GeoFrame | None) -> None:
        self.front = front
        self.building_id = building_id
        self.geo = geo
        # When the building's row was created: the batches carry it to the worker.
        self.created = ""
        self.alive = True
        self.counters = Counters()
        # Here: the time from publishing a batch to its receipt.
        self.latency = LatencyWindow()
        self.group_sizes = LatencyWindow()
        self._waiting = 0

    @property
    def queue_depth(self) -> int:
        """Batches published and not answered yet."""
        return self._waiting

    async def submit(self, submission: Submission) -> bytes:
        fields = batch_fields(submission)  # converted here: fronts scale out, workers do the tracking
        request, reply_to, future = self.front.request()
        started = time.perf_counter()
        self._waiting += 1
        try:
            try:
                await self.front.stream.publish(
                    self.front.js,
                    self.building_id,
                    messages.encode_stream_batch(reply_to, self.created, fields),
                )
            except NatsError as exc:
                raise ServiceUnavailableError(
                    f"the batch could not be queued for building {self.building_id!r} "
                    f"({type(exc).__name__}); send it again",
                    RETRY_AFTER_S,
                ) from None
            try:
                receipt: bytes = await asyncio.wait_for(future, self.front.timeout_s)
            except TimeoutError:
                raise ServiceUnavailableError(
                    f"building {self.building_id!r} did not answer within {self.front.timeout_s:g} s (its "
                    "worker may be being replaced); send the batch again: if it was applied meanwhile, the "
                    "answer is duplicate",
                    RETRY_AFTER_S,
                ) from None
        finally:
            self._waiting -= 1
            self.front.waiting.pop(request, None)
        self.latency.add(time.perf_counter() - started)
        return receipt

    async def ask(self, call: Call[T]) -> T:
        deadline = time.monotonic() + self.front.timeout_s
        try:
            while True:
                try:
                    msg = await self.front.connection.request(
                        calls_subject(self.building_id),
                        messages.encode_call(call),
                        timeout=max(0.1, deadline - time.monotonic()),
                    )
                    break
                except NoRespondersError:  # no worker holds it yet (new, or being taken over): wait a little
                    if time.monotonic() + NO_OWNER_POLL_S > deadline:
                        raise ServiceUnavailableError(
                            f"no worker holds building {self.building_id!r} right now (it is being taken "
                            "over); send the request again",
                            RETRY_AFTER_S,
                        ) from None
                    await asyncio.sleep(NO_OWNER_POLL_S)
        except (NatsTimeoutError, NatsError) as exc:
            raise ServiceUnavailableError(
                f"building {self.building_id!r} did not answer ({type(exc).__name__}); "
                "send the request again",
                RETRY_AFTER_S,
            ) from None
        answer: T = messages.decode_answer(msg.data)
        return answer

    def publish(self, messages_: list[LiveMessage]) -> None:
        """Messages an operator's call returned, to every front's dashboards."""
        self.front.relay(self.building_id, messages_)

    async def close(self) -> None:
        return None

    async def abandon(self) -> None:
        return None
