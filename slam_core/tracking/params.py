"""The tracker's parameters, and the modes an evaluation compares."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from slam_core.crowd.fingerprints import FingerprintParams
from slam_core.encounters.models import DetectionParams
from slam_core.encounters.selection import SelectionParams
from slam_core.filter.params import FilterParams
from slam_core.sensing.detectors import DetectorParams
from slam_core.sensing.pdr.online import PdrParams
from slam_core.tracking.floors import FloorParams
from slam_core.zones.presence import ZoneParams

MODES = ("pdr", "semanticslam", "dynamicslam")
"""How a user is tracked: ``pdr`` its own dead reckoning, ``semanticslam`` with the crowd's building anchors,
``dynamicslam`` also with human anchors and the crowd's WiFi fingerprints (other users' readings)."""
CROWD_SOLVERS = ("fusion", "graph")


@dataclass(frozen=True)
class ColdStartParams:
    """A phone with no start fix is placed by the crowd's fingerprint map (beyond both papers): at its first
    scan the map can place, its particles spread over the scan's k nearest stored scans (each
    ``candidate_sigma_m`` wide, those off the floor plan's walkable area weighed down), and it is tracked but
    not yet reported. It counts as placed once its estimate's larger sigma falls to ``confident_sigma_m``.
    Needs the fingerprint map (dynamicslam)."""

    enabled: bool = False
    """Off by default: on the shipped floors a phone placed this way was often placed far from where it
    was (``docs/experiments.md``), and a wrong confident position is worse than none."""
    candidate_sigma_m: float = 4.0
    """The fingerprint map's cell: a stored scan stands for a place about this wide."""
    confident_sigma_m: float = 5.0
    inject: float = 0.1
    """Share of a placing user's least likely particles drawn anew among each scan's candidates."""

    def __post_init__(self) -> None:
        if not (self.candidate_sigma_m > 0 and self.confident_sigma_m > 0):
            raise ValueError("cold start sigmas must be positive")


@dataclass(frozen=True)
class TrackerParams:
    filter: FilterParams = field(default_factory=FilterParams)
    detection: DetectionParams = field(default_factory=DetectionParams)
    selection: SelectionParams = field(default_factory=SelectionParams)
    """Which detections become human anchors (``slam_core.encounters.selection``)."""
    crowd_solver: str = "graph"
    graph_solve_period_ms: int = 5_000
    """The joint crowd-map solve runs at most every 5 s of phone time (it takes ~0.1 s)."""
    max_graph_users: int = 500
    """Users whose detections the joint solve keeps; older users' tracks are forgotten (their anchors keep
    their estimates), so a long-running server's solve stays bounded."""
    start_sigma_floor_m: float = 0.5
    pdr: PdrParams = field(default_factory=PdrParams)
    detectors: DetectorParams | None = field(default_factory=DetectorParams)
    """Building-anchor detectors for raw-IMU phones; None: steps only."""
    signature_sigma_m: float = 6.0
    """How far from a transmitter its visit's strongest reading may be (one sigma). On the msindoor floor the
    peak of a visit lies from the median position of that transmitter's strong readings 2.9 / 5.1 / 7.4 m
    (p50 / p75 / p90) for beacons and 3.7 / 6.8 / 9.8 m for WiFi APs: one sigma near the p75, the tail
    left to the gate."""
    signature_gate_chi2: float = 9.21
    """A signature observation more than this (99 %, 2 dof) from the user's cloud is skipped and counted."""
    fingerprints: FingerprintParams = field(default_factory=FingerprintParams)
    """The crowd-learned WiFi fingerprint map and its robust position fixes
    (``slam_core.crowd.fingerprints``). Off here, so that the core's defaults are the paper's DynamicSLAM;
    the server and ``evaluate --msindoor`` turn it on in dynamicslam mode."""
    cold_start: ColdStartParams = field(default_factory=ColdStartParams)
    floors: FloorParams = field(default_factory=FloorParams)
    """Each user's belief over the building's floors (``slam_core.tracking.floors``)."""
    zones: ZoneParams = field(default_factory=ZoneParams)
    """When a user is in a zone (``slam_core.zones.presence``)."""
    revise_headings: bool = True
    """When the PDR front-end's north offset estimate moves, translate the user's particles by the revision
    of the path dead-reckoned since its last absolute observation (``BuildingTracker._revise_headings``)."""

    def __post_init__(self) -> None:
        if self.crowd_solver not in CROWD_SOLVERS:
            raise ValueError(f"unknown crowd solver {self.crowd_solver!r}; valid: {', '.join(CROWD_SOLVERS)}")


def in_mode(params: TrackerParams, mode: str, fingerprint_fixes: bool = True) -> TrackerParams:
    """The parameters in a mode (``MODES``): human anchors and, if ``fingerprint_fixes``, fixes on the
    crowd's fingerprint map in ``dynamicslam`` only, both being other users' readings; ``semanticslam`` and
    ``pdr`` track on building anchors (``pdr`` is then scored on plain dead reckoning)."""
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; valid: {', '.join(MODES)}")
    others = mode == "dynamicslam"
    return replace(
        params,
        filter=replace(params.filter, use_human_anchors=others),
        fingerprints=replace(params.fingerprints, enabled=fingerprint_fixes and others),
    )
