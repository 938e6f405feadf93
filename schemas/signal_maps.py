"""A SignalSLAM map build over a building's recordings, as the operator API reports it."""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from pydantic import Field

from schemas.common import Identifier, UtcDatetime, WireModel, wire_config

SIGNAL_MAP_JOB_EXAMPLE: dict[str, Any] = {
    "id": "3f9c2a71b0de",
    "building_id": "hq",
    "status": "done",
    "created_at": "2026-11-24T12:00:00Z",
    "finished_at": "2026-11-24T12:00:14Z",
    "recordings": 3,
    "segments": 41,
    "devices": 7,
    "scans": 1320,
    "access_points": 412,
    "files": ["signal_map_ap1.png", "signal_map_ap1.json", "fingerprints_5m.json", "trajectories.json"],
    "error": None,
}


class SignalMapStatus(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


class SignalMapJob(WireModel):
    """One build: queued, running in its own process, then done (its files listed) or failed (why)."""

    model_config = wire_config(SIGNAL_MAP_JOB_EXAMPLE)

    id: Identifier
    building_id: Identifier
    status: SignalMapStatus
    created_at: UtcDatetime
    finished_at: UtcDatetime | None = None
    recordings: int = Field(ge=0, description="MCAP files the build reads.")
    segments: int | None = Field(
        default=None, ge=0, description="Walks between two landmarks that were solved."
    )
    segments_across_floors: int | None = Field(
        default=None, ge=0, description="Walks whose two landmarks are on different floors: left out."
    )
    floors: list[int] = Field(
        default_factory=list,
        description="The floors mapped; in a build of several, each floor's files start 'floor<level>_'.",
    )
    devices: int | None = Field(default=None, ge=0)
    scans: int | None = Field(default=None, ge=0)
    access_points: int | None = Field(default=None, ge=0)
    files: list[str] = Field(
        default_factory=list, description="Fetch each at .../signal-maps/{id}/files/{name}."
    )
    error: str | None = None
    radio_map_scans: int | None = Field(
        default=None,
        ge=0,
        description="Scans of this build's radio map that joined the building's tracker, once it has loaded "
        "it (None until then; a build that finished while the server was down is loaded when the building "
        "next loads, and is not counted here).",
    )
