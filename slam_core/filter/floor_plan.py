"""A floor plan as the motion update reads it: wall segments in a grid index, and the walkable area as a
raster.

Beyond both papers (neither uses a plan; IndoorAtlas, Situm and Anyplace do): a particle whose step crosses
a wall, or ends outside the walkable area, is made less likely (``FloorPlanParams``;
``slam_core.filter.kernels.walls``). The penalty is soft, because doors are not on the plan and walks do
enter shops.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MAX_RASTER_CELLS = 4_000_000
"""The walkable raster and the wall grid each hold at most this many cells: a large site gets coarser cells,
never a raster of gigabytes."""

PlanArrays = tuple[
    float,
    float,
    float,
    int,
    int,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    float,
    float,
    float,
    np.ndarray,
    np.ndarray,
    np.ndarray,
]
"""What the kernels take (``PlanIndex.arrays``), flat (a parallel kernel takes no nested tuple): the wall
grid's origin x, y, cells per metre, columns and rows, its CSR starts and wall indices, the walls (S, 4), the
raster's origin x, y and cells per metre, the raster (rows, columns) of uint8, and the wall grid's free cells
(uint8 per cell: no wall and wholly walkable), and the raster's summed-area table of unwalkable cells."""


@dataclass(frozen=True)
class PlanIndex:
    walls: np.ndarray
    """(S, 4) float64: x0, y0, x1, y1 in the local frame (metres), each segment once: adjacent obstacles
    draw their shared edge twice (on a mall floor, half of the segments), and a step crosses it once."""
    walkable_rings: tuple[np.ndarray, ...]
    """Rings (k, 2) bounding the walkable area by the even-odd rule (outline and holes); none: anywhere."""
    cell_m: float
    origin: tuple[float, float]
    grid_shape: tuple[int, int]
    """(rows, columns) of the wall grid."""
    cell_start: np.ndarray
    """(rows * columns + 1,) int64: cell c's walls are ``cell_walls[cell_start[c]:cell_start[c + 1]]``."""
    cell_walls: np.ndarray
    raster_m: float
    raster_origin: tuple[float, float]
    raster: np.ndarray
    """(rows, columns) uint8, 1 where walkable; (0, 0) when the plan has no walkable area."""
    free: np.ndarray
    """(rows * columns,) uint8 over the wall grid: 1 where a cell holds no wall and lies wholly in the
    walkable area. A user whose particles' steps all stay in free cells needs no test."""
    blocked_sum: np.ndarray
    """(rows + 1, columns + 1) int32 over the raster: blocked_sum[r, c] counts the unwalkable raster cells
    below row r and left of column c, so that whether a box is wholly walkable costs four reads."""
    axis_rad: float = 0.0
    """The walls' dominant direction modulo 90 degrees (counter-clockwise from east, in [0, pi/2)): most
    buildings are drawn on a grid, and their corridors follow it (``dominant_axis``)."""
    axis_strength: float = 0.0
    """How strongly the walls follow that grid: the length-weighted mean resultant of their directions taken
    four times (1: every wall on the grid; ~0: no grid, or no walls)."""

    @classmethod
    def build(
        cls,
        walls: np.ndarray,
        walkable_rings: Sequence[np.ndarray] = (),
        cell_m: float = 2.0,
        raster_m: float = 0.5,
    ) -> PlanIndex:
        """Index ``walls`` (S, 4) and rasterise the area inside ``walkable_rings`` (even-odd rule)."""
        walls = np.ascontiguousarray(walls, dtype=np.float64).reshape(-1, 4)
        rings = tuple(np.ascontiguousarray(r, dtype=np.float64).reshape(-1, 2) for r in walkable_rings)
        if not (np.all(np.isfinite(walls)) and all(np.all(np.isfinite(r)) for r in rings)):
            raise ValueError("floor plan: coordinates must be finite")
        if any(r.shape[0] < 3 for r in rings):
            raise ValueError("floor plan: a walkable ring needs at least three points")
        if not (cell_m > 0 and raster_m > 0):
            raise ValueError("floor plan: cell sizes must be positive")
        drawn, walls = walls, _distinct(walls)
        points = [walls[:, :2], walls[:, 2:], *rings]
        everything = np.concatenate(points) if sum(p.shape[0] for p in points) else np.zeros((1, 2))
        low, high = everything.min(axis=0), everything.max(axis=0)
        cell_m = _coarse_enough(cell_m, high - low)
        origin = (float(low[0] - cell_m), float(low[1] - cell_m))
        columns = math.ceil((high[0] - low[0]) / cell_m) + 3
        rows = math.ceil((high[1] - low[1]) / cell_m) + 3
        cell_start, cell_walls = _wall_grid(walls, origin, cell_m, rows, columns)
        if rings:
            ring_points = np.concatenate(rings)
            r_low, r_high = ring_points.min(axis=0), ring_points.max(axis=0)
            raster_m = _coarse_enough(raster_m, r_high - r_low)
            raster_origin = (float(r_low[0]), float(r_low[1]))
            raster = _rasterise(rings, raster_origin, raster_m, r_high)
        else:
            raster_origin, raster = (0.0, 0.0), np.zeros((0, 0), dtype=np.uint8)
        blocked_sum = _blocked_sum(raster)
        free = _free_cells(cell_start, origin, cell_m, rows, columns, blocked_sum, raster_origin, raster_m)
        axis_rad, axis_strength = dominant_axis(drawn)
        return cls(
            walls,
            rings,
            cell_m,
            origin,
            (rows, columns),
            cell_start,
            cell_walls,
            raster_m,
            raster_origin,
            raster,
            free,
            blocked_sum,
            axis_rad,
            axis_strength,
        )

    @classmethod
    def empty(cls) -> PlanIndex:
        """No walls, no area: every step is as likely as without a plan."""
        return cls.build(np.zeros((0, 4)))

    @property
    def is_empty(self) -> bool:
        return self.walls.shape[0] == 0 and self.raster.size == 0

    def arrays(self) -> PlanArrays:
        rows, columns = self.grid_shape
        return (
            self.origin[0],
            self.origin[1],
            1.0 / self.cell_m,
            columns,
            rows,
            self.cell_start,
            self.cell_walls,
            self.walls,
            self.raster_origin[0],
            self.raster_origin[1],
            1.0 / self.raster_m,
            self.raster,
            self.free,
            self.blocked_sum,
        )

    def walkable(self, xy: np.ndarray) -> np.ndarray:
        """Whether each point (n, 2) lies in the walkable area (all True without one), by the raster."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.raster.size == 0:
            return np.ones(xy.shape[0], dtype=bool)
        col = np.floor((xy[:, 0] - self.raster_origin[0]) / self.raster_m).astype(np.int64)
        row = np.floor((xy[:, 1] - self.raster_origin[1]) / self.raster_m).astype(np.int64)
        rows, columns = self.raster.shape
        inside = (col >= 0) & (col < columns) & (row >= 0) & (row < rows)
        out = np.zeros(xy.shape[0], dtype=bool)
        out[inside] = self.raster[row[inside], col[inside]] == 1
        return out


def dominant_axis(walls: np.ndarray) -> tuple[float, float]:
    """The walls' (S, 4) dominant direction modulo 90 degrees and its strength: the circular mean of four
    times each wall's direction, weighted by its length (a wall and its perpendicular count alike). Returns
    (axis in [0, pi/2), mean resultant length in [0, 1]); (0, 0) without walls."""
    d = walls[:, 2:4] - walls[:, 0:2]
    length = np.hypot(d[:, 0], d[:, 1])
    total = float(length.sum())
    if total <= 0.0:
        return 0.0, 0.0
    angle = 4.0 * np.arctan2(d[:, 1], d[:, 0])
    c, s = float(length @ np.cos(angle)) / total, float(length @ np.sin(angle)) / total
    return float((math.atan2(s, c) / 4.0) % (math.pi / 2)), float(min(1.0, math.hypot(c, s)))


def _coarse_enough(cell_m: float, span: np.ndarray) -> float:
    """``cell_m``, or the smallest size that keeps a grid over ``span`` within ``MAX_RASTER_CELLS``."""
    cells = (span[0] / cell_m + 3) * (span[1] / cell_m + 3)
    if cells <= MAX_RASTER_CELLS:
        return cell_m
    return float(math.sqrt(span[0] * span[1] / MAX_RASTER_CELLS)) + cell_m


MAX_WALL_CELLS = 20_000_000
"""Cells of the walls' bounding boxes a plan may span in all (a mall floor's: ~50,000); past it the plan is
refused before the index is built, which would hold every one of them in memory at once."""


def _wall_grid(
    walls: np.ndarray, origin: tuple[float, float], cell_m: float, rows: int, columns: int
) -> tuple[np.ndarray, np.ndarray]:
    """CSR of the walls each cell meets: a wall is listed in exactly the cells its segment passes through
    (or touches), found by clipping it to each cell of its bounding box (Liang-Barsky), every wall at once.
    A step tests only the walls of the cells its own box covers, so shorter lists are a faster motion
    update."""
    if walls.shape[0] == 0:
        return np.zeros(rows * columns + 1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    ox, oy = origin
    x0, y0, x1, y1 = walls.T
    c0 = np.floor((np.minimum(x0, x1) - ox) / cell_m).astype(np.int64)
    c1 = np.floor((np.maximum(x0, x1) - ox) / cell_m).astype(np.int64)
    r0 = np.floor((np.minimum(y0, y1) - oy) / cell_m).astype(np.int64)
    r1 = np.floor((np.maximum(y0, y1) - oy) / cell_m).astype(np.int64)
    width = c1 - c0 + 1
    sizes = width * (r1 - r0 + 1)
    total = int(sizes.sum())
    if total > MAX_WALL_CELLS:
        raise ValueError(
            f"floor plan: its walls' boxes span {total:,} cells of {cell_m:g} m; at most {MAX_WALL_CELLS:,}"
        )
    wall_of = np.repeat(np.arange(walls.shape[0]), sizes)
    within = np.arange(total) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    cc = c0[wall_of] + within % width[wall_of]
    rr = r0[wall_of] + within // width[wall_of]
    hit = _segment_meets_boxes(
        x0[wall_of], y0[wall_of], x1[wall_of], y1[wall_of],
        ox + cc * cell_m, oy + rr * cell_m, ox + (cc + 1) * cell_m, oy + (rr + 1) * cell_m,
    )  # fmt: skip
    keep = (hit | (sizes[wall_of] == 1)) & (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < columns)
    cells = rr[keep] * columns + cc[keep]
    order = np.argsort(cells, kind="stable")
    counts = np.bincount(cells, minlength=rows * columns)
    cell_start = np.zeros(rows * columns + 1, dtype=np.int64)
    np.cumsum(counts, out=cell_start[1:])
    return cell_start, np.ascontiguousarray(wall_of[keep][order], dtype=np.int64)


def _segment_meets_boxes(
    x0: np.ndarray,
    y0: np.ndarray,
    x1: np.ndarray,
    y1: np.ndarray,
    bx0: np.ndarray,
    by0: np.ndarray,
    bx1: np.ndarray,
    by1: np.ndarray,
) -> np.ndarray:
    """Whether each segment meets its closed box (Liang-Barsky clipping, vectorised)."""
    lo = np.zeros(bx0.shape)
    hi = np.ones(bx0.shape)
    ok = np.ones(bx0.shape, dtype=bool)
    for p, q_lo, q_hi in ((x1 - x0, x0 - bx0, bx1 - x0), (y1 - y0, y0 - by0, by1 - y0)):
        flat = p == 0.0
        ok &= ~flat | ((q_lo >= 0) & (q_hi >= 0))
        safe = np.where(flat, 1.0, p)
        t_a, t_b = -q_lo / safe, q_hi / safe
        lo = np.where(flat, lo, np.maximum(lo, np.minimum(t_a, t_b)))
        hi = np.where(flat, hi, np.minimum(hi, np.maximum(t_a, t_b)))
    result: np.ndarray = ok & (lo <= hi)
    return result


def _free_cells(
    cell_start: np.ndarray,
    origin: tuple[float, float],
    cell_m: float,
    rows: int,
    columns: int,
    blocked: np.ndarray,
    raster_origin: tuple[float, float],
    raster_m: float,
) -> np.ndarray:
    """1 for each wall-grid cell with no wall whose whole square is walkable (every raster cell it touches),
    by the summed-area table of the raster's unwalkable cells (``_blocked_sum``)."""
    free: np.ndarray = (np.diff(cell_start) == 0).astype(np.uint8)
    if blocked.size <= 1:  # no raster: no area, walkable everywhere
        return free
    raster_rows, raster_columns = blocked.shape[0] - 1, blocked.shape[1] - 1
    r, c = np.divmod(np.arange(rows * columns), columns)
    x0 = np.floor((origin[0] + c * cell_m - raster_origin[0]) / raster_m).astype(np.int64)
    x1 = np.floor((origin[0] + (c + 1) * cell_m - raster_origin[0]) / raster_m).astype(np.int64)
    y0 = np.floor((origin[1] + r * cell_m - raster_origin[1]) / raster_m).astype(np.int64)
    y1 = np.floor((origin[1] + (r + 1) * cell_m - raster_origin[1]) / raster_m).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x1 < raster_columns) & (y1 < raster_rows)
    x0, x1 = np.clip(x0, 0, raster_columns - 1), np.clip(x1, 0, raster_columns - 1)
    y0, y1 = np.clip(y0, 0, raster_rows - 1), np.clip(y1, 0, raster_rows - 1)
    count = blocked[y1 + 1, x1 + 1] - blocked[y0, x1 + 1] - blocked[y1 + 1, x0] + blocked[y0, x0]
    free &= (inside & (count == 0)).astype(np.uint8)
    return free


def _distinct(walls: np.ndarray) -> np.ndarray:
    """The walls without repeats, in their first drawing's order; a segment drawn the other way round is a
    repeat. Which copy stays changes no crossing test (its answer does not depend on the direction)."""
    if walls.shape[0] == 0:
        return walls
    forward = (walls[:, 0] < walls[:, 2]) | ((walls[:, 0] == walls[:, 2]) & (walls[:, 1] <= walls[:, 3]))
    canonical = np.where(forward[:, None], walls, walls[:, [2, 3, 0, 1]])
    _, first = np.unique(canonical, axis=0, return_index=True)
    return np.ascontiguousarray(walls[np.sort(first)])


def _blocked_sum(raster: np.ndarray) -> np.ndarray:
    """The raster's summed-area table of unwalkable cells, (rows + 1, columns + 1) int32 with a zero first row
    and column; (1, 1) for a plan without an area."""
    blocked = np.zeros((raster.shape[0] + 1, raster.shape[1] + 1), dtype=np.int32)
    blocked[1:, 1:] = np.cumsum(np.cumsum(raster == 0, axis=0, dtype=np.int32), axis=1, dtype=np.int32)
    return blocked


def _rasterise(
    rings: tuple[np.ndarray, ...], origin: tuple[float, float], cell_m: float, high: np.ndarray
) -> np.ndarray:
    """Scan-line fill by the even-odd rule: a cell is walkable when its centre is inside."""
    columns = math.ceil((high[0] - origin[0]) / cell_m) + 1
    rows = math.ceil((high[1] - origin[1]) / cell_m) + 1
    edges = np.concatenate([np.hstack([r, np.roll(r, -1, axis=0)]) for r in rings])
    x0, y0, x1, y1 = edges.T
    raster = np.zeros((rows, columns), dtype=np.uint8)
    centres_x = origin[0] + (np.arange(columns) + 0.5) * cell_m
    for row in range(rows):
        yc = origin[1] + (row + 0.5) * cell_m
        spans = ((y0 <= yc) & (yc < y1)) | ((y1 <= yc) & (yc < y0))
        if not spans.any():
            continue
        xs = np.sort(x0[spans] + (yc - y0[spans]) * (x1[spans] - x0[spans]) / (y1[spans] - y0[spans]))
        inside = np.searchsorted(xs, centres_x, side="right") % 2 == 1
        raster[row, inside] = 1
    return raster
