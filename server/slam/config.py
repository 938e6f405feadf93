"""The engine as the settings configure it (the tracker's parameters, the encounter range models), and as an
evaluation runs it (a mode, a number of particles, seeds)."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

from server.settings import Settings
from slam_core.encounters.models import Calibration, DetectionParams
from slam_core.filter.params import (
    BuildingAnchorParams,
    FilterParams,
    HumanAnchorParams,
    MotionParams,
    extended_confusion,
)
from slam_core.tracking.params import MODES, ColdStartParams, TrackerParams, in_mode


def load_calibration(path: Path | None) -> Calibration:
    """Encounter range models from ``crowdslam calibrate`` (``path``), or the shipped testbed calibration."""
    if path is None:
        text = resources.files("server.data").joinpath("testbed_calibration.json").read_text()
    else:
        text = path.read_text()
    return Calibration.from_dict(json.loads(text))


def tracker_params(settings: Settings) -> TrackerParams:
    n_types = len(extended_confusion(10))
    params = TrackerParams(
        filter=FilterParams(anchors=BuildingAnchorParams(confusion=extended_confusion(n_types))),
        detection=DetectionParams(wifi_model=settings.encounter_wifi_model),
        cold_start=ColdStartParams(enabled=settings.cold_start),
    )
    return in_mode(params, settings.mode, settings.fingerprint_fixes)


WARM_PICKS = ("earliest", "alternate")


@dataclass(frozen=True)
class ReplayOptions:
    mode: str = "dynamicslam"
    warm_split: float | None = None
    """The earliest fraction of each floor's walks (by start time) that first builds the building's map; the
    rest is scored (``warm_pick`` "earliest": a building on its first day, the hard case)."""
    warm_pick: str = "earliest"
    """Which walks warm the crowd: "earliest" (``warm_split``'s fraction) or "alternate" (every other walk of
    each floor by start time, the first included: a building walked everywhere, as after a month of use)."""
    particles: int = 75
    sampling: str = "iterative"
    motion_model: str = "bias-scale"
    crowd_solver: str = "graph"
    seed: int = 0
    """The world's (a simulated crowd's) and, unless ``filter_seed`` is set, the filters' seed."""
    filter_seed: int | None = None
    """The filters' own seed, to measure their noise on one world (``seed``) apart from the world's."""
    window_ms: int = 1000
    fingerprints: bool = True
    """In ``dynamicslam`` mode, also localise scans on the crowd-learned WiFi fingerprint map
    (``slam_core.crowd.fingerprints``), as the server does by default."""
    liars: int = 0
    """Simulated users who lie (``server.simulation.liars``); only the honest users are scored."""
    floor_plan: bool = True
    """Weigh steps by the floor's plan where the world has one (the data set's ``geojson_map.json``)."""
    start_fix: bool = True
    """Start each scored walk at its first waypoint; off, the phones are placed by the crowd's map
    (``ColdStartParams``) and scored from their first waypoint on."""
    radio_map: bool = False
    """With a warm split: build the warm walks into a radio map (SignalSLAM, tagged at each walk's first and
    last waypoints) that the tracker loads before the scored walks."""
    zones: bool = False
    """Draw zones (each room's or shop's frontage) and score the visits the tracker tells against the true
    ones, and against a point test of the estimates (``slam_core.zones.visits.ZoneTally``)."""
    heading_axes: bool = False
    """Weigh each straight stretch of a walk by the plan's grid (``FloorPlanParams.heading_axes``; off by
    default: it did not help on both shipped floors)."""

    @property
    def tracker_seed(self) -> int:
        return self.seed if self.filter_seed is None else self.filter_seed

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"unknown mode {self.mode!r}; valid: {', '.join(MODES)}")
        if self.liars < 0:
            raise ValueError("liars must be >= 0")
        if self.warm_split is not None and not 0.0 < self.warm_split < 1.0:
            raise ValueError("warm_split must be in (0, 1)")
        if self.warm_pick not in WARM_PICKS:
            raise ValueError(f"unknown warm_pick {self.warm_pick!r}; valid: {', '.join(WARM_PICKS)}")
        if self.warm_pick == "alternate" and self.warm_split is not None:
            raise ValueError(
                "warm_split is the earliest walks' share; warm_pick 'alternate' warms every other walk"
            )

    @property
    def warms(self) -> bool:
        """Whether some walks first warm the crowd and only the others are scored."""
        return self.warm_split is not None or self.warm_pick == "alternate"

    def warm_walks(self, n: int) -> list[bool]:
        """Of a floor's ``n`` walks sorted by start time, which warm the crowd."""
        if self.warm_pick == "alternate":
            return [k % 2 == 0 for k in range(n)]
        n_warm = 0 if self.warm_split is None else int(n * self.warm_split)
        return [k < n_warm for k in range(n)]


def replay_params(base: TrackerParams, options: ReplayOptions) -> TrackerParams:
    """The server's tracker parameters (``base``) in the options' mode: ``pdr`` scores plain dead reckoning,
    ``semanticslam`` uses building anchors only, ``dynamicslam`` also human anchors and (unless the options
    turn them off) fixes on the crowd's WiFi fingerprint map, which come from other users' scans too."""
    params = replace(
        base,
        filter=replace(
            base.filter,
            n_particles=options.particles,
            motion=MotionParams(model=options.motion_model),
            human=HumanAnchorParams(sampling=options.sampling),
            floor_plan=replace(base.filter.floor_plan, heading_axes=options.heading_axes),
        ),
        crowd_solver=options.crowd_solver,
        # a scored walk without its start fix is placed by the crowd's map, whatever the server's default
        cold_start=replace(base.cold_start, enabled=base.cold_start.enabled or not options.start_fix),
    )
    return in_mode(params, options.mode, options.fingerprints)
