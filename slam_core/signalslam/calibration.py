"""PDR recalibration between two landmarks, SignalSLAM Section II-B, Eq. 4.

Between landmarks I and J the stride d and the pocket offset angle beta are assumed constant and found by
grid search so that dead reckoning from y_I lands nearest y_J:
(d, beta) = argmin || x_hat_J(d_hat, beta_hat) - y_J ||   (Eq. 4).
Our steps come with their own (Weinberg) lengths, so the stride is a scale on them; the grid is finer than the
paper's (0.1 m, 5 deg) because one cell of 5 deg is already 8.7 % of the distance walked sideways.

Beyond the paper (``CalibrationPrior``): Eq. 4 is ill-posed when the two landmarks are close together (a walk
that comes back near its start: half the scored waypoints of msindoor site1 F1). Any rotation then lands near
y_J, and the grid search picks one at random within +-45 deg; recalibration made those walks worse than raw
PDR (3.2 m p50 against 2.6 m). With a prior the search minimises the posterior instead,
||x_hat_J - y_J||^2 / sigma_J^2 + ((d - 1) / sigma_d)^2 + (beta / sigma_beta)^2, where sigma_J is the spread
the per-step noise leaves at J. The prior's figures are what the phones' PDR is known to do (the bias-scale
motion model's priors); on a long straight walk the landmark term dominates and the result is Eq. 4's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slam_core.filter.params import MotionParams


@dataclass(frozen=True)
class CalibrationGrid:
    scales: np.ndarray = field(default_factory=lambda: np.arange(0.6, 1.6001, 0.01))
    offsets_rad: np.ndarray = field(default_factory=lambda: np.radians(np.arange(-45.0, 45.001, 1.0)))


@dataclass(frozen=True)
class CalibrationPrior:
    scale_sigma: float = MotionParams.step_scale_sigma
    """Step-scale error of a walk: the engine's bias-scale prior (msindoor: sigma ~0.14)."""
    offset_sigma_rad: float = MotionParams.heading_bias_sigma_rad
    """Heading bias of a walk left after the phone's north reference: the engine's bias-scale prior
    (msindoor: |bias| p50 7 deg)."""
    step_sigma_m: float = 0.11
    """Per-step position noise that does not come from scale or bias (a step's length noise of ~0.1 m and
    0.05 m across, combined): the landmark J is matched to within sqrt(N) of it. The graph's own along-step
    sigma is wider (``SignalGraphParams.step_sigma_along_m``, an upper bound measured against the
    waypoints)."""
    landmark_sigma_m: float = 0.5
    """Each landmark's own position error."""

    def __post_init__(self) -> None:
        if min(self.scale_sigma, self.offset_sigma_rad, self.step_sigma_m, self.landmark_sigma_m) <= 0:
            raise ValueError("calibration prior sigmas must be positive")


def calibrate_segment(
    lengths: np.ndarray,
    headings: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
    grid: CalibrationGrid,
    prior: CalibrationPrior | None = None,
) -> tuple[float, float, float]:
    """(scale, offset in rad, residual in m) minimising Eq. 4 over the grid, or with ``prior`` the posterior
    described in the module docstring. ``headings`` are the steps' directions (rad, counter-clockwise from
    east); the offset is added to each."""
    lengths = np.asarray(lengths, dtype=float)
    headings = np.asarray(headings, dtype=float)
    if lengths.shape != headings.shape or lengths.ndim != 1 or lengths.size == 0:
        raise ValueError("lengths and headings must be non-empty 1-D arrays of the same length")
    walked = np.array([lengths @ np.cos(headings), lengths @ np.sin(headings)])
    target = np.asarray(end, dtype=float) - np.asarray(start, dtype=float)
    c, s = np.cos(grid.offsets_rad), np.sin(grid.offsets_rad)
    rotated = np.stack([c * walked[0] - s * walked[1], s * walked[0] + c * walked[1]], axis=-1)  # (B, 2)
    ends = grid.scales[:, None, None] * rotated[None, :, :]  # (S, B, 2)
    residual = np.linalg.norm(ends - target, axis=-1)
    cost = residual
    if prior is not None:
        sigma_end2 = lengths.size * prior.step_sigma_m**2 + 2 * prior.landmark_sigma_m**2
        cost = (
            residual**2 / sigma_end2
            + ((grid.scales[:, None] - 1.0) / prior.scale_sigma) ** 2
            + (grid.offsets_rad[None, :] / prior.offset_sigma_rad) ** 2
        )
    i, j = np.unravel_index(np.argmin(cost), cost.shape)
    return float(grid.scales[i]), float(grid.offsets_rad[j]), float(residual[i, j])


def dead_reckon(lengths: np.ndarray, headings: np.ndarray, start: np.ndarray, scale: float = 1.0,
                offset: float = 0.0) -> np.ndarray:  # fmt: skip
    """Positions after each step (N, 2) from ``start``, with the stride scale and heading offset applied."""
    h = np.asarray(headings, dtype=float) + offset
    steps = scale * np.asarray(lengths, dtype=float)[:, None] * np.column_stack([np.cos(h), np.sin(h)])
    positions: np.ndarray = np.asarray(start, dtype=float) + np.cumsum(steps, axis=0)
    return positions
