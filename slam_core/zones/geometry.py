"""Zones as the kernels read them: simple polygons on floors, concatenated, each with its bounding box; the
check that a ring is a zone at all; and the share of a particle cloud inside each zone of its floor.

A zone is "inside" for a user with a probability, not a yes or no (beyond both papers, which track places,
not areas): the weighted share of the user's particles that lie in the polygon. The particles, not the
estimate's covariance, because a cloud being placed is multimodal, zones are not convex (an L-shaped ward,
a shop around a corner), and a Gaussian's mass in a polygon has no closed form; 75 particles give the share
to a few per cent, which is what a threshold of 0.8 or 0.2 needs. Pure numerics.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

MAX_VERTICES = 512
"""A zone's outline has at most this many vertices (a shop front needs four; a traced ward, dozens)."""


@dataclass(frozen=True)
class ZoneSet:
    """Z zones: their floors, their outlines concatenated (zone z's vertices are ``start[z]:start[z + 1]`` of
    ``vx``, ``vy``, the ring not closed) and their bounding boxes (x0, y0, x1, y1)."""

    level: np.ndarray
    start: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    bbox: np.ndarray

    def __len__(self) -> int:
        return int(self.level.size)

    @staticmethod
    def empty() -> ZoneSet:
        return zone_set([], [])


def ring_problem(ring: np.ndarray) -> str | None:
    """Why a ring (K, 2), closed or not, is no zone's outline, or None: fewer than three distinct vertices,
    more than ``MAX_VERTICES``, a coordinate not finite, no area, or two edges that cross or touch (a
    self-intersecting outline has no inside one can tell people about)."""
    ring = np.asarray(ring, dtype=np.float64)
    if ring.ndim != 2 or ring.shape[1] != 2:
        return "an outline is a list of [x, y] positions"
    if ring.shape[0] > 1 and np.array_equal(ring[0], ring[-1]):
        ring = ring[:-1]
    if not np.all(np.isfinite(ring)):
        return "an outline's coordinates must be finite numbers"
    if ring.shape[0] < 3:
        return "an outline needs at least three distinct positions"
    if ring.shape[0] > MAX_VERTICES:
        return f"an outline may have at most {MAX_VERTICES} positions, not {ring.shape[0]}"
    if np.linalg.matrix_rank(ring - ring[0], tol=1e-9) < 2:
        return "the outline encloses no area: its positions lie on one line"
    crossing = _first_crossing(ring[:, 0].copy(), ring[:, 1].copy())
    if crossing[0] >= 0:
        i, j = crossing
        return f"the outline crosses itself: its edges {i} and {j} (from position 0) meet"
    if abs(_area(ring[:, 0], ring[:, 1])) < 1e-6:
        return "the outline encloses no area"
    return None


def zone_set(rings: list[np.ndarray], levels: list[int], names: list[str] | None = None) -> ZoneSet:
    """The zones' arrays, in the given order; ValueError naming the first ring that is no outline (by its
    zone's name in ``names``, else by its index)."""
    if len(rings) != len(levels) or (names is not None and len(names) != len(rings)):
        raise ValueError("one floor (and name, where named) per zone")
    starts, xs, ys = [0], [], []
    for k, ring in enumerate(rings):
        problem = ring_problem(ring)
        if problem is not None:
            raise ValueError(f"zone {k if names is None else repr(names[k])}: {problem}")
        ring = np.asarray(ring, dtype=np.float64)
        if np.array_equal(ring[0], ring[-1]):
            ring = ring[:-1]
        xs.append(ring[:, 0])
        ys.append(ring[:, 1])
        starts.append(starts[-1] + ring.shape[0])
    vx = np.concatenate(xs) if xs else np.zeros(0)
    vy = np.concatenate(ys) if ys else np.zeros(0)
    start = np.asarray(starts, dtype=np.int64)
    bbox = np.array(
        [[vx[a:b].min(), vy[a:b].min(), vx[a:b].max(), vy[a:b].max()] for a, b in itertools.pairwise(start)]
    ).reshape(-1, 4)
    return ZoneSet(np.asarray(levels, dtype=np.int64).reshape(-1), start, vx, vy, bbox)


def _area(x: np.ndarray, y: np.ndarray) -> float:
    """The ring's signed area (shoelace)."""
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


@njit(cache=True, nogil=True)
def _orientation(ax: float, ay: float, bx: float, by: float, cx: float, cy: float) -> int:
    v = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    return 0 if v == 0.0 else (1 if v > 0.0 else -1)


@njit(cache=True, nogil=True)
def _on_segment(ax: float, ay: float, bx: float, by: float, cx: float, cy: float) -> bool:
    """Whether c, collinear with a-b, lies on the segment a-b."""
    return min(ax, bx) <= cx <= max(ax, bx) and min(ay, by) <= cy <= max(ay, by)


@njit(cache=True, nogil=True)
def _segments_meet(
    ax: float, ay: float, bx: float, by: float, cx: float, cy: float, dx: float, dy: float
) -> bool:
    o1 = _orientation(ax, ay, bx, by, cx, cy)
    o2 = _orientation(ax, ay, bx, by, dx, dy)
    o3 = _orientation(cx, cy, dx, dy, ax, ay)
    o4 = _orientation(cx, cy, dx, dy, bx, by)
    if o1 != o2 and o3 != o4:
        return True
    return (
        (o1 == 0 and _on_segment(ax, ay, bx, by, cx, cy))
        or (o2 == 0 and _on_segment(ax, ay, bx, by, dx, dy))
        or (o3 == 0 and _on_segment(cx, cy, dx, dy, ax, ay))
        or (o4 == 0 and _on_segment(cx, cy, dx, dy, bx, by))
    )


@njit(cache=True, nogil=True)
def _first_crossing(x: np.ndarray, y: np.ndarray) -> tuple[int, int]:
    """The first pair of the ring's edges (i, j), i < j, that meet other than at the vertex two neighbours
    share; (-1, -1) for a simple ring. Edge i runs from vertex i to vertex i + 1 (the last back to 0)."""
    n = x.size
    for i in range(n):
        ax, ay, bx, by = x[i], y[i], x[(i + 1) % n], y[(i + 1) % n]
        for j in range(i + 1, n):
            cx, cy, dx, dy = x[j], y[j], x[(j + 1) % n], y[(j + 1) % n]
            if j == i + 1 or (i == 0 and j == n - 1):  # neighbours share one vertex: meeting elsewhere counts
                shared_x, shared_y = (bx, by) if j == i + 1 else (ax, ay)
                far_x, far_y = (dx, dy) if j == i + 1 else (cx, cy)
                other_x, other_y = (ax, ay) if j == i + 1 else (bx, by)
                # they overlap only when collinear and folding back over each other
                if _orientation(other_x, other_y, shared_x, shared_y, far_x, far_y) == 0 and (
                    (far_x - shared_x) * (other_x - shared_x) + (far_y - shared_y) * (other_y - shared_y)
                    > 0.0
                ):
                    return i, j
                continue
            if _segments_meet(ax, ay, bx, by, cx, cy, dx, dy):
                return i, j
    return -1, -1


@njit(cache=True, nogil=True)
def _inside(px: float, py: float, vx: np.ndarray, vy: np.ndarray, a: int, b: int) -> bool:
    """Even-odd ray casting: whether (px, py) is inside the ring of vertices a..b-1."""
    inside = False
    j = b - 1
    for i in range(a, b):
        yi, yj = vy[i], vy[j]
        if (yi > py) != (yj > py):
            x_cross = vx[i] + (py - yi) * (vx[j] - vx[i]) / (yj - yi)
            if px < x_cross:
                inside = not inside
        j = i
    return inside


@njit(cache=True, nogil=True, parallel=True)
def inside_shares(
    px: np.ndarray,
    py: np.ndarray,
    logw: np.ndarray,
    users: np.ndarray,
    user_level: np.ndarray,
    zone_level: np.ndarray,
    start: np.ndarray,
    vx: np.ndarray,
    vy: np.ndarray,
    bbox: np.ndarray,
) -> np.ndarray:
    """(U, Z): for each of ``users`` (rows of the particle arrays ``px``, ``py``, ``logw``, on floor
    ``user_level``), the normalised weight of its particles inside each zone of its floor (0 for the other
    floors' zones). A zone whose box misses the cloud's box costs one comparison."""
    n_users, n_zones = users.size, zone_level.size
    out = np.zeros((n_users, n_zones))
    for k in prange(n_users):
        u = users[k]
        m = px.shape[1]
        top = -math.inf
        x0, y0, x1, y1 = math.inf, math.inf, -math.inf, -math.inf
        for p in range(m):
            top = max(top, logw[u, p])
            x0, x1 = min(x0, px[u, p]), max(x1, px[u, p])
            y0, y1 = min(y0, py[u, p]), max(y1, py[u, p])
        total = 0.0
        for p in range(m):
            total += math.exp(logw[u, p] - top)
        for z in range(n_zones):
            if zone_level[z] != user_level[k]:
                continue
            if bbox[z, 0] > x1 or bbox[z, 2] < x0 or bbox[z, 1] > y1 or bbox[z, 3] < y0:
                continue
            share = 0.0
            for p in range(m):
                x, y = px[u, p], py[u, p]
                in_box = bbox[z, 0] <= x <= bbox[z, 2] and bbox[z, 1] <= y <= bbox[z, 3]
                if in_box and _inside(x, y, vx, vy, start[z], start[z + 1]):
                    share += math.exp(logw[u, p] - top)
            out[k, z] = share / total
    return out


def points_inside(zones: ZoneSet, x: np.ndarray, y: np.ndarray, level: np.ndarray) -> np.ndarray:
    """(N, Z): whether each point (on floor ``level``) lies inside each zone: the point test of a platform
    that decides "inside" from one estimate (or from the truth), the same test as a particle's."""
    x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 1)
    y = np.ascontiguousarray(y, dtype=np.float64).reshape(-1, 1)
    n = x.shape[0]
    if n == 0 or len(zones) == 0:
        return np.zeros((n, len(zones)), dtype=np.bool_)
    shares = inside_shares(
        x,
        y,
        np.zeros((n, 1)),
        np.arange(n, dtype=np.int64),
        np.ascontiguousarray(level, dtype=np.int64).reshape(-1),
        zones.level,
        zones.start,
        zones.vx,
        zones.vy,
        zones.bbox,
    )
    return shares > 0.5
