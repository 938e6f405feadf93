"""The floor plan's likelihood of one particle's step (``slam_core.filter.floor_plan``): walls it crosses, and
whether it ends in the walkable area. Beyond both papers."""

from __future__ import annotations

import math

from numba import njit

from slam_core.filter.floor_plan import PlanArrays


@njit(cache=True, nogil=True, inline="always")
def _orientation(ax: float, ay: float, bx: float, by: float, px: float, py: float) -> float:
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@njit(cache=True, nogil=True)
def crosses_wall(plan: PlanArrays, x0: float, y0: float, x1: float, y1: float) -> bool:
    """Whether the step (x0, y0) -> (x1, y1) properly crosses a wall (touching is not crossing). Only the
    walls listed in the grid cells the step's bounding box covers are tested."""
    ox, oy, cell, columns, rows = plan[0], plan[1], plan[2], plan[3], plan[4]
    cell_start, cell_walls, walls = plan[5], plan[6], plan[7]
    if walls.shape[0] == 0:
        return False
    c0 = max(0, math.floor((min(x0, x1) - ox) / cell))
    c1 = min(columns - 1, math.floor((max(x0, x1) - ox) / cell))
    r0 = max(0, math.floor((min(y0, y1) - oy) / cell))
    r1 = min(rows - 1, math.floor((max(y0, y1) - oy) / cell))
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


@njit(cache=True, nogil=True)
def walkable(plan: PlanArrays, x: float, y: float) -> bool:
    """Whether (x, y) is in the walkable area (everywhere when the plan has none)."""
    rx, ry, raster_m, raster = plan[8], plan[9], plan[10], plan[11]
    rows, columns = raster.shape
    if rows == 0:
        return True
    c = math.floor((x - rx) / raster_m)
    r = math.floor((y - ry) / raster_m)
    if c < 0 or c >= columns or r < 0 or r >= rows:
        return False
    return bool(raster[r, c] == 1)


@njit(cache=True, nogil=True)
def step_log_likelihood(
    plan: PlanArrays, x0: float, y0: float, x1: float, y1: float, log_crossing: float, log_outside: float
) -> float:
    """The plan's log-likelihood of a step: ``log_crossing`` if it crosses a wall, plus ``log_outside`` if it
    ends outside the walkable area; 0 otherwise."""
    out = 0.0
    if crosses_wall(plan, x0, y0, x1, y1):
        out += log_crossing
    if not walkable(plan, x1, y1):
        out += log_outside
    return out
