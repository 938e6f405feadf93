"""The buildings being tracked, as the API reaches them: one worker per building, loaded on first use, on a
thread of this process (``server.buildings.workers``) or in a process of its own
(``server.buildings.process``).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Protocol

from sqlalchemy.orm import Session, sessionmaker

from server.buildings.config import TrackingConfig
from server.buildings.process import ProcessBuildingWorker
from server.buildings.tracking import BuildingTracking
from server.buildings.workers import BuildingWorker, Worker
from server.errors import NotFoundError
from server.live.broadcast import Broadcaster
from server.recordings.recorder import BuildingRecorder
from server.settings import Settings
from server.store import repositories as repo


class Buildings(Protocol):
    """What the API reaches buildings through: ``TrackingService`` here, or a cluster front's
    ``server.cluster.front.ClusterBuildings`` (the buildings' workers elsewhere)."""

    async def worker(self, building_id: str) -> Worker: ...
    @property
    def workers(self) -> dict[str, Worker]: ...
    async def close(self) -> None: ...


class TrackingService:
    """The registry of buildings being tracked; a building is loaded on first use."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        broadcaster: Broadcaster,
        config: TrackingConfig,
        recordings: Path | None = None,
        processes: Settings | None = None,
        kernel_threads: int | None = None,
    ) -> None:
        """``processes``: run each building in a process of its own, configured by these settings;
        otherwise on a thread whose kernels use ``kernel_threads`` numba threads (None: numba's default)."""
        self._processes = processes
        self._kernel_threads = kernel_threads
        self._config = config
        self._recordings = recordings
        self._sessions = sessions
        self._broadcaster = broadcaster
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
                if not await asyncio.to_thread(self._exists, building_id):  # never a process for nothing
                    raise NotFoundError(f"no building {building_id!r}")
                worker = await ProcessBuildingWorker.start(building_id, self._processes, self._broadcaster)
                self._workers[building_id] = worker
            elif worker is None:
                recorder = (
                    None if self._recordings is None else BuildingRecorder(self._recordings, building_id)
                )
                building = await asyncio.to_thread(
                    BuildingTracking, building_id, self._sessions, self._config, recorder
                )
                worker = self._workers[building_id] = BuildingWorker(
                    building, self._broadcaster, self._kernel_threads
                )
        return worker

    def _exists(self, building_id: str) -> bool:
        with self._sessions() as session:
            return repo.get_building(session, building_id) is not None

    @property
    def workers(self) -> dict[str, Worker]:
        return dict(self._workers)

    async def unload(self, building_id: str, snapshot: bool = True) -> None:
        """Stop tracking the building here: with a snapshot (a clean handoff), or without (its lease was
        lost: another worker owns it and writes its state now)."""
        async with self._loading:
            worker = self._workers.pop(building_id, None)
        if worker is not None:
            await (worker.close() if snapshot else worker.abandon())

    async def close(self) -> None:
        for worker in self._workers.values():
            await worker.close()
        self._workers.clear()
