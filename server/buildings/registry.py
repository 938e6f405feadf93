"""The buildings being tracked, as the API reaches them: one handle per building, loaded on first use, on a
thread of this process (``server.buildings.handles``) or in a process of its own
(``server.buildings.process``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass
from typing import Protocol

from sqlalchemy.orm import Session, sessionmaker

from schemas.api import FailingBuilding
from server.buildings.handles import BuildingHandle, BuildingThread
from server.buildings.host import BuildingHost, tracking_config
from server.buildings.process import BuildingLoadError, BuildingProcess
from server.errors import BuildingUnavailableError, NotFoundError
from server.live.broadcast import Broadcaster
from server.recordings.recorder import BuildingRecorder
from server.settings import Settings
from server.store import repositories as repo

logger = logging.getLogger(__name__)

LOAD_RETRY_S = 10.0
"""A building that could not be loaded is tried again at the first request this long after: until then its
requests answer 503 at once (with this ``Retry-After``), costing nothing."""


@dataclass
class LoadFailure:
    """A building that could not be loaded (the error is logged): how often, when last, and when to try."""

    failures: int
    last_unix_s: float
    retry_at: float
    """``time.monotonic()`` from which a request tries to load it again."""


DEGRADED_S = 300.0
"""A building that refused a batch this recently makes the server ``degraded``."""


class Buildings(Protocol):
    """What the API reaches buildings through: ``TrackingService`` here, or a cluster front's
    ``server.cluster.front.ClusterBuildings`` (the buildings on the cluster's workers)."""

    async def handle(self, building_id: str) -> BuildingHandle: ...
    @property
    def handles(self) -> dict[str, BuildingHandle]: ...
    @property
    def load_failures(self) -> dict[str, LoadFailure]:
        """The buildings that could not be loaded here lately (none once loaded)."""
        ...

    async def close(self) -> None: ...


class TrackingService:
    """The registry of buildings being tracked; a building is loaded on first use."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        broadcaster: Broadcaster,
        settings: Settings,
        *,
        in_processes: bool,
        kernel_threads: int | None = None,
    ) -> None:
        """Buildings tracked as ``settings`` say, each ``in_processes`` of its own, or else on a thread of
        this process whose kernels use ``kernel_threads`` numba threads (None: numba's default)."""
        self._settings = settings
        self._in_processes = in_processes
        self._config = tracking_config(settings)
        self._recordings = settings.recordings_dir if settings.record else None
        self._kernel_threads = kernel_threads
        self._sessions = sessions
        self._broadcaster = broadcaster
        self._handles: dict[str, BuildingHandle] = {}
        self._load_failures: dict[str, LoadFailure] = {}
        self._loading = asyncio.Lock()

    async def handle(self, building_id: str) -> BuildingHandle:
        """The building's handle, loaded on first use. A building that cannot be loaded answers
        ``BuildingUnavailableError`` (503), and is tried again after ``LOAD_RETRY_S``."""
        handle = self._handles.get(building_id)
        if handle is not None and handle.alive:
            return handle
        async with self._loading:
            handle = self._handles.get(building_id)
            if handle is not None and handle.alive:
                return handle
            if handle is not None:  # its process died: start it again
                del self._handles[building_id]
                await handle.close()
            failure = self._load_failures.get(building_id)
            now = time.monotonic()
            if failure is not None and now < failure.retry_at:
                raise BuildingUnavailableError(building_id, failure.retry_at - now)
            try:
                handle = await self._open(building_id)
            except NotFoundError:
                raise
            except Exception as exc:
                count = 1 if failure is None else failure.failures + 1
                self._load_failures[building_id] = LoadFailure(
                    count, time.time(), time.monotonic() + LOAD_RETRY_S
                )
                if not isinstance(exc, BuildingLoadError):  # a building's process logged its own
                    logger.error("building %s could not be loaded", building_id, exc_info=exc)
                raise BuildingUnavailableError(building_id, LOAD_RETRY_S) from None
            self._load_failures.pop(building_id, None)
            self._handles[building_id] = handle
        return handle

    async def _open(self, building_id: str) -> BuildingHandle:
        """Load the building in a process of its own or on a thread of this one."""
        if self._in_processes:
            if not await asyncio.to_thread(self._exists, building_id):  # never a process for nothing
                raise NotFoundError(f"no building {building_id!r}")
            return await BuildingProcess.start(building_id, self._settings, self._broadcaster)
        recorder = None if self._recordings is None else BuildingRecorder(self._recordings, building_id)
        host = await asyncio.to_thread(BuildingHost, building_id, self._sessions, self._config, recorder)
        return BuildingThread(host, self._broadcaster, self._kernel_threads)

    @property
    def load_failures(self) -> dict[str, LoadFailure]:
        return dict(self._load_failures)

    def _exists(self, building_id: str) -> bool:
        with self._sessions() as session:
            return repo.get_building(session, building_id) is not None

    @property
    def handles(self) -> dict[str, BuildingHandle]:
        return dict(self._handles)

    async def unload(self, building_id: str, snapshot: bool = True) -> None:
        """Stop tracking the building here: with a snapshot (a clean handoff), or without (its lease was
        lost: another worker owns it and writes its state now)."""
        async with self._loading:
            handle = self._handles.pop(building_id, None)
        if handle is not None:
            await (handle.close() if snapshot else handle.abandon())

    async def close(self) -> None:
        for handle in self._handles.values():
            await handle.close()
        self._handles.clear()


def failing_buildings(tracking: Buildings, now: float) -> list[FailingBuilding]:
    """The buildings that cannot be loaded, and those that failed a batch (live, or replaying their log)
    in the last ``DEGRADED_S``."""
    found: dict[str, FailingBuilding] = {}
    for building_id, handle in tracking.handles.items():
        counters = handle.counters
        if (counters.failed_batches or counters.replay_failures) and (
            now - counters.last_failure_unix_s < DEGRADED_S
        ):
            found[building_id] = FailingBuilding(
                building_id=building_id,
                failed_batches=counters.failed_batches,
                unreplayed_batches=counters.replay_failures,
                last_failure_ms=int(counters.last_failure_unix_s * 1000),
            )
    for building_id, failure in tracking.load_failures.items():
        found[building_id] = FailingBuilding(
            building_id=building_id,
            failed_batches=0,
            failed_loads=failure.failures,
            last_failure_ms=int(failure.last_unix_s * 1000),
        )
    return [found[b] for b in sorted(found)]
