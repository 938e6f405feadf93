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
def _cell_span(
    grid: tuple[float, float, float, int, int], low_x: float, low_y: float, high_x: float, high_y: float
) -> tuple[int, int, int, int]:
    """The first and last column and row of the wall grid's cells the box covers, clamped to the grid."""
    ox, oy, per_m, columns, rows = grid
    c0 = max(0, math.floor((low_x - ox) * per_m))
    c1 = min(columns - 1, math.floor((high_x - ox) * per_m))
    r0 = max(0, math.floor((low_y - oy) * per_m))
    r1 = min(rows - 1, math.floor((high_y - oy) * per_m))
    return c0, c1, r0, r1


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
    columns = grid[3]
    c0, c1, r0, r1 = _cell_span(grid, min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))
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


MAX_NEAR_WALLS = 32
"""The walls a user's steps are tested against one by one (``near_walls``); a user near more is tested through
the grid."""


@njit(cache=True, nogil=True, inline="always")
def near_walls(
    grid: tuple[float, float, float, int, int],
    cell_start: np.ndarray,
    cell_walls: np.ndarray,
    walls: np.ndarray,
    low_x: float,
    low_y: float,
    high_x: float,
    high_y: float,
    near: np.ndarray,
) -> int:
    """Copy into ``near`` (MAX_NEAR_WALLS, 4) the walls, once each, that are listed in the grid cells the box
    covers and whose own box meets it; returns how many, or -1 when there are more than ``near`` holds. A step
    inside the box can only cross these: testing a user's particles against this short list, instead of
    looking each step up in the grid, gives the same answers at a fraction of the cost."""
    columns = grid[3]
    c0, c1, r0, r1 = _cell_span(grid, low_x, low_y, high_x, high_y)
    n = 0
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            cell_index = r * columns + c
            for k in range(cell_start[cell_index], cell_start[cell_index + 1]):
                w = cell_walls[k]
                ax, ay, bx, by = walls[w, 0], walls[w, 1], walls[w, 2], walls[w, 3]
                if max(ax, bx) < low_x or min(ax, bx) > high_x or max(ay, by) < low_y or min(ay, by) > high_y:
                    continue
                seen = False
                for j in range(n):
                    if near[j, 0] == ax and near[j, 1] == ay and near[j, 2] == bx and near[j, 3] == by:
                        seen = True
                        break
                if seen:
                    continue
                if n == near.shape[0]:
                    return -1
                near[n, 0], near[n, 1], near[n, 2], near[n, 3] = ax, ay, bx, by
                n += 1
    return n


@njit(cache=True, nogil=True)
def mark_crossings(
    near: np.ndarray,
    n: int,
    x0: np.ndarray,
    y0: np.ndarray,
    x1: np.ndarray,
    y1: np.ndarray,
    hit: np.ndarray,
) -> None:
    """hit[m] = 1.0 if step m, (x0[m], y0[m]) -> (x1[m], y1[m]), properly crosses one of the ``n`` walls
    ``near_walls`` listed, else 0.0: ``crosses_wall``'s test, wall by wall over all the steps without a
    branch, which the compiler runs several steps at a time."""
    for m in range(hit.shape[0]):
        hit[m] = 0.0
    for k in range(n):
        ax, ay, bx, by = near[k, 0], near[k, 1], near[k, 2], near[k, 3]
        for m in range(hit.shape[0]):
            px, py, qx, qy = x0[m], y0[m], x1[m], y1[m]
            d1 = _orientation(ax, ay, bx, by, px, py)
            d2 = _orientation(ax, ay, bx, by, qx, qy)
            d3 = _orientation(px, py, qx, qy, ax, ay)
            d4 = _orientation(px, py, qx, qy, bx, by)
            if (d1 * d2 < 0.0) & (d3 * d4 < 0.0):
                hit[m] = 1.0


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


@njit(cache=True, nogil=True, inline="always")
def wholly_walkable(
    frame: tuple[float, float, float],
    raster: np.ndarray,
    blocked_sum: np.ndarray,
    low_x: float,
    low_y: float,
    high_x: float,
    high_y: float,
) -> bool:
    """Whether every raster cell the box covers is walkable (``walkable`` then holds at every point in it),
    from the summed-area table of unwalkable cells; a box reaching past the raster is not. Everywhere when the
    plan has no area."""
    rows, columns = raster.shape
    if rows == 0:
        return True
    rx, ry, per_m = frame
    c0, c1 = math.floor((low_x - rx) * per_m), math.floor((high_x - rx) * per_m)
    r0, r1 = math.floor((low_y - ry) * per_m), math.floor((high_y - ry) * per_m)
    if c0 < 0 or r0 < 0 or c1 >= columns or r1 >= rows:
        return False
    blocked = (
        blocked_sum[r1 + 1, c1 + 1] - blocked_sum[r0, c1 + 1] - blocked_sum[r1 + 1, c0] + blocked_sum[r0, c0]
    )
    return bool(blocked == 0)
