"""A served building as its host's parts share it: its tracker and bookkeeping as loaded from SQL (replaced
at once by a reload), where it is stored, and how its tracker's state reads on the wire."""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import AbstractContextManager

from sqlalchemy.orm import Session, sessionmaker

from schemas.anchors import BuildingAnchor
from schemas.estimates import Estimate, EstimateSource
from schemas.live import LiveMessage
from server.buildings import snapshot as tracker_snapshot
from server.buildings.config import TrackingConfig
from server.buildings.counters import Counters
from server.buildings.recovery import Loaded
from server.errors import NotFoundError
from server.ingestion import convert
from server.recordings.recorder import BuildingRecorder
from slam_core.tracking.tracker import EstimateRow

SaveSnapshot = Callable[[Session], list[dict[str, object]]]
"""Writes the building's snapshot in the caller's transaction; returns the device rows it wrote, which the
ledger counts saved once that transaction commits (``BuildingHost.save_snapshot``)."""


def commit_with_snapshot(
    building: Building,
    save_snapshot: SaveSnapshot,
    reload: Callable[[], None],
    write: Callable[[Session], object],
) -> None:
    """An edit the tracker has already taken (an anchor, a plan, a zone): its rows and a snapshot in one
    transaction, so a restart replays the batches after it with the edit and none before it. If it fails,
    the tracker goes back to what SQL holds (the edit undone) and the error is raised."""
    try:
        with building.writer_turns, building.sessions.begin() as session:
            write(session)
            rows = save_snapshot(session)
    except Exception:
        reload()
        raise
    building.devices.saved(rows)


class Building:
    """One building's shared state. Its parts (``server.buildings.host``: the batch path, anchor edits,
    floor plans, users, upkeep) read and change it from the building's one thread, each its own concern; a
    reload (``adopt``) replaces the loaded state whole, which each part sees at once."""

    def __init__(
        self,
        building_id: str,
        sessions: sessionmaker[Session],
        config: TrackingConfig,
        counters: Counters,
        recorder: BuildingRecorder | None,
        writer_turns: AbstractContextManager[object],
    ) -> None:
        self.building_id = building_id
        self.sessions = sessions
        self.config = config
        self.counters = counters
        self.recorder = recorder
        self.writer_turns = writer_turns
        """Taken around every write transaction of the batch path and the operators' edits
        (``server.store.writer_turns``)."""

    def adopt(self, loaded: Loaded) -> None:
        """The state ``Recovery.load`` gives: the tracker, anchor ids, devices, frame, extent, history
        sampling, each user's device and the count of tracker calls."""
        self.tracker = loaded.tracker
        self.ids = loaded.ids
        self.devices = loaded.devices
        self.geo = loaded.geo
        self.extent = loaded.extent
        self.history = loaded.history
        self.device_of_user = loaded.device_of_user
        self.tracker_call = loaded.tracker_call
        self.told: list[LiveMessage] = []
        """Live messages of transactions outside the batch path (zone exits of users forgotten idle before a
        snapshot), told with the next group's: a reload drops them with the state they came from."""

    def take_told(self) -> list[LiveMessage]:
        told, self.told = self.told, []
        return told

    def state(self) -> tracker_snapshot.BuildingState:
        """What a snapshot holds: the tracker and the building's bookkeeping, as of its last tracker call."""
        return tracker_snapshot.BuildingState(
            self.tracker,
            dict(self.ids.public),
            dict(self.ids.labels),
            dict(self.device_of_user),
            self.tracker_call,
            dict(self.history.latest_t_ms),
        )

    def context(self) -> convert.BuildingContext:
        """What converting a batch needs of the building now (``convert.building_context``)."""
        return convert.building_context(self.building_id, self.tracker, self.ids.index, self.geo, self.extent)

    # ------------------------------------------------------------------ the tracker on the wire
    def anchor(self, index: int) -> BuildingAnchor:
        """The crowd map's anchor ``index`` as the API shows it (a learned anchor gets its public id now)."""
        crowd = self.tracker.crowd
        mean, cov, type_index, known, count, last = crowd.anchor(index)
        return convert.building_anchor(
            self.ids.public_id(index),
            self.building_id,
            mean,
            cov,
            type_index,
            known,
            count,
            int(last) if math.isfinite(last) and last > 0 else None,
            self.ids.labels.get(index),
            floor=crowd.level(index),
            signature=crowd.signature(index) or None,
        )

    def live_anchor(self, public_id: str) -> int:
        """The crowd index of a live anchor; ``NotFoundError`` for a deleted, merged or unknown one."""
        index = self.ids.index.get(public_id)
        if index is None or not self.tracker.crowd.is_live(index):
            raise NotFoundError(f"no anchor {public_id!r} in building {self.building_id!r}")
        return index

    def estimate(self, user: str, row: EstimateRow) -> Estimate:
        source = (
            EstimateSource.DYNAMICSLAM
            if self.tracker.params.filter.use_human_anchors
            else EstimateSource.SEMANTICSLAM
        )
        return convert.estimate(
            row, self.building_id, user, self.device_of_user.get(user, user), self.geo, source
        )

    def latest_estimate(self, user: str) -> Estimate | None:
        """The user's estimate, once placed (a phone started without a fix is not reported until then)."""
        row = self.tracker.estimate(user) if self.tracker.is_placed(user) else None
        return None if row is None else self.estimate(user, row)
