"""The floor plan's likelihood of one particle's step (``slam_core.filter.floor_plan``): walls it crosses, and
whether it ends in the walkable area. Beyond both papers.

The motion kernel unpacks the plan's arrays once per user and passes them on: taking an array out of the
plan's tuple inside the particle loop counted a reference each time, and cost more than the tests."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _orientation(ax: float, ay: float, bx: float, by: float, px: float, py: float) -> float:
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@njit(cache=True, nogil=True, inline="always")
def crosses_wall(
    grid: tuple[float, float, float, int, int],
    cell_start: np.ndarray,
    cell_walls: np.ndarray,
    walls: np.ndarray,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
) -> bool:
    """Whether the step (x0, y0) -> (x1, y1) properly crosses a wall (touching is not crossing). Only the
    walls listed in the grid cells (origin x, y, 1 / cell size, columns, rows) the step's box covers are
    tested; most steps stay in one cell, often without walls, and test none."""
    ox, oy, per_m, columns, rows = grid
    c0 = max(0, math.floor((min(x0, x1) - ox) * per_m))
    c1 = min(columns - 1, math.floor((max(x0, x1) - ox) * per_m))
    r0 = max(0, math.floor((min(y0, y1) - oy) * per_m))
    r1 = min(rows - 1, math.floor((max(y0, y1) - oy) * per_m))
    if c0 == c1 and r0 == r1:  # the common case, without the loops
        first = r0 * columns + c0
        if cell_start[first] == cell_start[first + 1]:
            return False
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            cell_index = r * columns + c
            for k in range(cell_start[cell_index], cell_start[cell_index + 1]):
                w = cell_walls[k]
                ax, ay, bx, by = walls[w, 0], walls[w, 1], walls[w, 2], walls[w, 3]
                d1 = _orientation(ax, ay, bx, by, x0, y0)
                d2 = _orientation(ax, ay, bx, by, x1, y1)
                if d1 * d2 >= 0.0:
                    continue
                d3 = _orientation(x0, y0, x1, y1, ax, ay)
                d4 = _orientation(x0, y0, x1, y1, bx, by)
                if d3 * d4 < 0.0:
                    return True
    return False


@njit(cache=True, nogil=True, inline="always")
def walkable(frame: tuple[float, float, float], raster: np.ndarray, x: float, y: float) -> bool:
    """Whether (x, y) is in the walkable area (raster origin x, y and 1 / cell size; everywhere when the
    plan has no area)."""
    rows, columns = raster.shape
    if rows == 0:
        return True
    rx, ry, per_m = frame
    c = math.floor((x - rx) * per_m)
    r = math.floor((y - ry) * per_m)
    if c < 0 or c >= columns or r < 0 or r >= rows:
        return False
    return bool(raster[r, c] == 1)


@njit(cache=True, nogil=True, inline="always")
def all_free(
    grid: tuple[float, float, float, int, int],
    free: np.ndarray,
    low_x: float,
    low_y: float,
    high_x: float,
    high_y: float,
) -> bool:
    """Whether every wall-grid cell the box covers is free (no wall, wholly walkable): then no step inside
    it crosses a wall or ends off the walkable area. A box reaching past the grid is not free."""
    ox, oy, per_m, columns, rows = grid
    c0, c1 = math.floor((low_x - ox) * per_m), math.floor((high_x - ox) * per_m)
    r0, r1 = math.floor((low_y - oy) * per_m), math.floor((high_y - oy) * per_m)
    if c0 < 0 or r0 < 0 or c1 >= columns or r1 >= rows:
        return False
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            if free[r * columns + c] == 0:
                return False
    return True
