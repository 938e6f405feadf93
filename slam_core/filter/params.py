"""Filter parameters as frozen dataclasses. Defaults are DynamicSLAM's Table 2 values where the paper gives
one; every other default says where it comes from."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MOTION_MODELS = ("paper", "bias-scale")
SAMPLING_METHODS = ("one-shot", "iterative")
PEER_SELECTIONS = ("most-confident", "all")

# The paper testbed's five anchor types; the server's anchor types map onto these indices.
ANCHOR_TYPES = ("elevator", "stairs", "door", "turn", "magnetic")


@dataclass(frozen=True)
class MotionParams:
    """Motion update, Eq. 4-8.

    ``paper``: each step samples L ~ N(l, sigma_l) and a heading change phi ~ N(phi_hat, sigma_phi) (Eq. 5)
    and integrates them (Eq. 6-8).

    ``bias-scale`` (beyond the paper): real phones drift mostly through a constant heading bias per walk and a
    step-length scale error (measured on the msindoor traces: bias sigma ~12 deg, scale sigma ~0.14). Each
    particle carries a heading bias b ~ N(0, heading_bias_sigma) and a scale k ~ N(1, step_scale_sigma),
    drawn once; a step moves it by L = k l + N(0, sigma_l) along heading phi_obs + b + r, where r is a slow
    per-particle random walk. Anchors then select particles with the right bias and scale, correcting the
    cause of the drift rather than only its effect. Where a floor plan weighs the steps, the scale prior is
    ``FloorPlanParams.step_scale_sigma`` instead: walls select short scales, not right ones. (The per-step
    white heading noise sigma_phi is the paper model's; here it is negligible against the walk and is left
    out.)
    """

    model: str = "bias-scale"
    step_length_sigma_m: float = 0.05
    heading_change_sigma_rad: float = math.radians(2.0)
    heading_bias_sigma_rad: float = math.radians(10.0)
    step_scale_sigma: float = 0.12
    heading_walk_sigma_rad: float = math.radians(0.5)
    """Per-step random walk of the heading error in the bias-scale model (per sqrt(step))."""
    start_heading_sigma_rad: float = math.radians(10.0)
    """Prior on the initial heading in the paper model (relative headings only)."""

    def __post_init__(self) -> None:
        if self.model not in MOTION_MODELS:
            raise ValueError(f"unknown motion model {self.model!r}; valid: {', '.join(MOTION_MODELS)}")
        for name in (
            "step_length_sigma_m",
            "heading_change_sigma_rad",
            "heading_bias_sigma_rad",
            "step_scale_sigma",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")


@dataclass(frozen=True)
class HumanAnchorParams:
    """Human anchors (Algorithm 1, Eq. 9-14).

    The paper updates with the EKF proposal only. Real encounters are often wrong (~18 % of Eq. 3 detections
    on the msindoor traces are within 5 m), so the likelihood used for the weights is a mixture
    ``(1 - outlier_probability) N(z; z_hat, S) + outlier_probability / max_range_m`` and an encounter whose
    user-level Mahalanobis distance exceeds ``gate_sigma`` is not applied at all.
    """

    sampling: str = "iterative"  # Table 2
    beta_m: float = 0.1  # Table 2: iterative sampling stops when successive updates differ by less than beta
    max_iterations: int = 10
    peer_selection: str = "most-confident"  # Section 5.1
    outlier_probability: float = 0.2
    max_range_m: float = 60.0
    gate_sigma: float = 3.0
    control_covariance_cap_m2: float = 25.0
    """P_t (Eq. 11) is the covariance of the control data since the particle's last correction, capped."""

    def __post_init__(self) -> None:
        if self.sampling not in SAMPLING_METHODS:
            raise ValueError(f"unknown sampling {self.sampling!r}; valid: {', '.join(SAMPLING_METHODS)}")
        if self.peer_selection not in PEER_SELECTIONS:
            raise ValueError(
                f"unknown peer selection {self.peer_selection!r}; valid: {', '.join(PEER_SELECTIONS)}"
            )
        if not 0.0 <= self.outlier_probability < 1.0:
            raise ValueError("outlier_probability must be in [0, 1)")
        if self.beta_m <= 0 or self.max_iterations < 1:
            raise ValueError("beta_m must be > 0 and max_iterations >= 1")


def _default_confusion() -> np.ndarray:
    # p(detected | true) for the five testbed types, rows = true type (the scenario's matrix).
    return np.array(
        [
            [0.80, 0.10, 0.04, 0.03, 0.03],
            [0.10, 0.80, 0.04, 0.03, 0.03],
            [0.04, 0.04, 0.80, 0.06, 0.06],
            [0.03, 0.03, 0.06, 0.82, 0.06],
            [0.03, 0.03, 0.06, 0.06, 0.82],
        ]
    )


def extended_confusion(n_types: int, other_correct: float = 0.9) -> np.ndarray:
    """p(detected | true) over ``n_types`` types: the testbed's matrix for its five types, and for each
    further type (escalator, beacon, WiFi, organic and tag signatures from the front-end) ``other_correct``
    on the diagonal with the rest spread evenly over the other types. The paper gives no confusion for
    these; 0.9 is about its testbed's diagonal."""
    base = _default_confusion()
    if n_types < base.shape[0]:
        raise ValueError(f"need at least the {base.shape[0]} testbed types")
    out = np.zeros((n_types, n_types))
    out[: base.shape[0], : base.shape[0]] = base
    for f in range(base.shape[0], n_types):
        out[f, :] = (1.0 - other_correct) / (n_types - 1)
        out[f, f] = other_correct
    return out


@dataclass(frozen=True)
class BuildingAnchorParams:
    """Building anchors: data association (Eq. 15-16), Map_Update (Algorithm 3), weights (Eq. 17)."""

    detection_sigma_m: float = 0.5
    """R_t = sigma^2 I: a detection says the user is within the detection radius r of the anchor; a point
    uniform on a disc of radius r = 1 m has a per-axis standard deviation of r / 2."""
    new_anchor_likelihood: float = 1e-3
    """p0 of Eq. 16 (per m^2, comparable with the Gaussian densities of Eq. 15)."""
    confusion: np.ndarray = field(default_factory=_default_confusion)
    """p(detected type | true type); Eq. 15 uses p(f | f_hat), its column-normalised posterior."""
    capacity: int = 48
    """Anchors per particle map; a full map counts the overflow and creates no new anchor."""
    known_sigma_m: float = 0.01
    """Operator-known anchors are exact (Theorem 3); a centimetre keeps the algebra well conditioned."""

    def __post_init__(self) -> None:
        c = np.asarray(self.confusion, dtype=np.float64)
        if c.ndim != 2 or c.shape[0] != c.shape[1] or np.any(c < 0) or not np.allclose(c.sum(axis=1), 1.0):
            raise ValueError("confusion must be a square matrix of probabilities whose rows sum to 1")
        if self.capacity < 1:
            raise ValueError("capacity must be >= 1")

    @property
    def type_posterior(self) -> np.ndarray:
        """p(true f | detected f_hat) under a uniform prior: entry [f, f_hat]."""
        c = np.asarray(self.confusion, dtype=np.float64)
        posterior: np.ndarray = c / c.sum(axis=0, keepdims=True)
        return posterior


RESAMPLING_SCHEMES = ("systematic", "stratified", "residual", "multinomial")


@dataclass(frozen=True)
class ResamplingParams:
    scheme: str = "systematic"
    ess_threshold: float = 0.5
    """Resample when the effective sample size falls below this fraction of M; 1.0 resamples at every
    update, as Algorithm 2 (lines 23-25) does."""
    roughening_bias_rad: float = math.radians(1.0)
    roughening_scale: float = 0.01
    """Beyond the paper: after a resampling, each particle's heading bias and step scale get a small jitter
    (roughening, Gordon et al. 1993). Without it resampling collapses their diversity, clouds become
    overconfident, and a user whose error exceeds the cloud's spread no longer associates even a known
    anchor (seen on the testbed: users 7-10 m off after passing known anchors)."""

    def __post_init__(self) -> None:
        if self.scheme not in RESAMPLING_SCHEMES:
            raise ValueError(
                f"unknown resampling scheme {self.scheme!r}; valid: {', '.join(RESAMPLING_SCHEMES)}"
            )
        if not 0.0 < self.ess_threshold <= 1.0:
            raise ValueError("ess_threshold must be in (0, 1]")


@dataclass(frozen=True)
class FloorPlanParams:
    """Beyond both papers: how a floor plan weighs each particle's step (``slam_core.filter.floor_plan``).
    Soft, because doors are not on a plan and walks enter shops: a step through a wall keeps
    ``wall_crossing_likelihood`` of its weight, a step ending outside the walkable area
    ``outside_likelihood``. The same for every building; nothing is fitted to a floor."""

    wall_crossing_likelihood: float = 0.1
    outside_likelihood: float = 0.01
    step_scale_sigma: float = 0.05
    """The step-scale prior of a user admitted where a plan weighs the steps, in place of
    ``MotionParams.step_scale_sigma``. The walls cannot tell a walk's scale, and they bias it: a path shrunk
    about its start keeps farther from every wall, so the particles that survive them walk short. On the
    real walks of both shipped floors the filter's scale fell from 0.98 to 0.94 over a walk while the
    surveyed one was 1.02, and the scale error ended larger than the prior's; without a plan it fell less
    (to 0.97). A narrower prior leaves the walls less to bias (``docs/experiments.md``). Without a plan the
    anchors learn the scale, as on the simulated testbed, so the wider prior stays there."""
    heading_axes: bool = False
    """Weigh each straight stretch of a user's walk by how well it follows the plan's grid
    (``DynamicSlam.observe_heading_axis``): heuristic drift elimination (Borenstein et al., 2009) as a
    particle likelihood. A phone's heading is off by a bias that stays for the walk (sigma ~12 deg on the
    real walks), and the corridors of a building drawn on a grid run along it."""
    axis_sigma_rad: float = math.radians(8.0)
    """Spread of a stretch's direction about the grid when the stretch follows it."""
    axis_share: float = 0.3
    """The share of straight stretches that follow the grid; the rest cross open space at any angle (an
    outlier term, uniform over the 90 degrees)."""
    axis_min_strength: float = 0.5
    """Plans whose walls follow a grid less than this (``slam_core.filter.floor_plan.dominant_axis``) give no
    heading observation."""
    stretch_m: float = 15.0
    """A straight stretch is observed once it is this long; the next one starts after it."""
    stretch_turn_rad: float = math.radians(20.0)
    """A step further than this from its stretch's direction ends the stretch (a turn)."""

    def __post_init__(self) -> None:
        for name in ("wall_crossing_likelihood", "outside_likelihood"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in (0, 1]")
        if self.step_scale_sigma < 0:
            raise ValueError("step_scale_sigma must be >= 0")
        if not 0.0 < self.axis_share < 1.0:
            raise ValueError("axis_share must be in (0, 1)")
        if not (self.axis_sigma_rad > 0 and self.stretch_m > 0 and self.stretch_turn_rad > 0):
            raise ValueError("axis_sigma_rad, stretch_m and stretch_turn_rad must be > 0")
        if not 0.0 <= self.axis_min_strength <= 1.0:
            raise ValueError("axis_min_strength must be in [0, 1]")

    @property
    def log_weights(self) -> tuple[float, float]:
        return math.log(self.wall_crossing_likelihood), math.log(self.outside_likelihood)


@dataclass(frozen=True)
class FilterParams:
    n_particles: int = 75  # Table 2
    motion: MotionParams = field(default_factory=MotionParams)
    human: HumanAnchorParams = field(default_factory=HumanAnchorParams)
    anchors: BuildingAnchorParams = field(default_factory=BuildingAnchorParams)
    resampling: ResamplingParams = field(default_factory=ResamplingParams)
    floor_plan: FloorPlanParams = field(default_factory=FloorPlanParams)
    use_human_anchors: bool = True
    """False gives the paper's baseline, SemanticSLAM (building anchors only)."""

    def __post_init__(self) -> None:
        if self.n_particles < 1:
            raise ValueError("n_particles must be >= 1")
