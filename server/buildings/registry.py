"""The buildings being tracked, as the API reaches them: one handle per building, loaded on first use, on a
thread of this process (``server.buildings.handles``) or in a process of its own
(``server.buildings.process``).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Protocol

from sqlalchemy.orm import Session, sessionmaker

from server.buildings.config import TrackingConfig
from server.buildings.handles import BuildingHandle, BuildingThread
from server.buildings.host import BuildingHost
from server.buildings.process import BuildingProcess
from server.errors import NotFoundError
from server.live.broadcast import Broadcaster
from server.recordings.recorder import BuildingRecorder
from server.settings import Settings
from server.store import repositories as repo


class Buildings(Protocol):
    """What the API reaches buildings through: ``TrackingService`` here, or a cluster front's
    ``server.cluster.front.ClusterBuildings`` (the buildings on the cluster's workers)."""

    async def handle(self, building_id: str) -> BuildingHandle: ...
    @property
    def handles(self) -> dict[str, BuildingHandle]: ...
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
        self._handles: dict[str, BuildingHandle] = {}
        self._loading = asyncio.Lock()

    async def handle(self, building_id: str) -> BuildingHandle:
        handle = self._handles.get(building_id)
        if handle is not None and handle.alive:
            return handle
        async with self._loading:
            handle = self._handles.get(building_id)
            if handle is not None and not handle.alive:  # its process died: start it again
                await handle.close()
                handle = None
            if handle is None and self._processes is not None:
                if not await asyncio.to_thread(self._exists, building_id):  # never a process for nothing
                    raise NotFoundError(f"no building {building_id!r}")
                handle = await BuildingProcess.start(building_id, self._processes, self._broadcaster)
                self._handles[building_id] = handle
            elif handle is None:
                recorder = (
                    None if self._recordings is None else BuildingRecorder(self._recordings, building_id)
                )
                host = await asyncio.to_thread(
                    BuildingHost, building_id, self._sessions, self._config, recorder
                )
                handle = self._handles[building_id] = BuildingThread(
                    host, self._broadcaster, self._kernel_threads
                )
        return handle

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
