"""PDR recalibration between two landmarks, SignalSLAM Section II-B, Eq. 4.

Between landmarks I and J the stride d and the pocket offset angle beta are assumed constant and found by
grid search so that dead reckoning from y_I lands nearest y_J:
(d, beta) = argmin || x_hat_J(d_hat, beta_hat) - y_J ||   (Eq. 4).
Our steps come with their own (Weinberg) lengths, so the stride is a scale on them; the grid is finer than the
paper's (0.1 m, 5 deg) because one cell of 5 deg is already 8.7 % of the distance walked sideways.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class CalibrationGrid:
    scales: np.ndarray = field(default_factory=lambda: np.arange(0.6, 1.6001, 0.01))
    offsets_rad: np.ndarray = field(default_factory=lambda: np.radians(np.arange(-45.0, 45.001, 1.0)))


def calibrate_segment(
    lengths: np.ndarray, headings: np.ndarray, start: np.ndarray, end: np.ndarray, grid: CalibrationGrid
) -> tuple[float, float, float]:
    """(scale, offset in rad, residual in m) minimising Eq. 4 over the grid. ``headings`` are the steps'
    directions (rad, counter-clockwise from east); the offset is added to each."""
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
    i, j = np.unravel_index(np.argmin(residual), residual.shape)
    return float(grid.scales[i]), float(grid.offsets_rad[j]), float(residual[i, j])


def dead_reckon(lengths: np.ndarray, headings: np.ndarray, start: np.ndarray, scale: float = 1.0,
                offset: float = 0.0) -> np.ndarray:  # fmt: skip
    """Positions after each step (N, 2) from ``start``, with the stride scale and heading offset applied."""
    h = np.asarray(headings, dtype=float) + offset
    steps = scale * np.asarray(lengths, dtype=float)[:, None] * np.column_stack([np.cos(h), np.sin(h)])
    positions: np.ndarray = np.asarray(start, dtype=float) + np.cumsum(steps, axis=0)
    return positions
