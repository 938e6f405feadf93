"""A building of several storeys in simulation: the ways between floors, the walks that take them, and the
barometer that sees them (the scenario's ``storeys`` section; ``server/data/three-floors.json``).

Every floor has the scenario's corridor grid. Three ways join the floors, each placed at corridor nodes by
the world's seed:

- **a stairwell**: a switchback flight at one node, walked out along a corridor and back while climbing one
  storey (short steps, the phone's step detector still counts them);
- **a lift** at another node, to any other floor: the user waits, stands while it rides, and walks out;
- **a pair of escalators** on one corridor segment: the up one from a step past its foot node towards its top
  node, the down one beside it back; the user steps on, stands while it carries them along and up (the phone
  counts no steps for that distance), and steps off.

Pressure is the standard atmosphere's at the phone's height, on the building's pressure (which drifts with
the weather over the run), plus each phone's own offset and noise. Pure numerics: the caller loads the
scenario; the randomness is its generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

SEA_LEVEL_HPA = 1013.25
Node = tuple[int, int]


@dataclass(frozen=True)
class Links:
    """Where the ways between floors are, as corridor nodes (grid indices)."""

    stairs: Node
    stairs_towards: Node  # the neighbouring node the flight runs towards (and back)
    lift: Node
    escalator_foot: Node
    escalator_top: Node  # a neighbour of the foot: the up escalator runs from the foot towards it


@dataclass(frozen=True)
class StoreyWalk:
    """One user's walk through the storeys, as samples of the true path: ``t`` from the walk's start (s),
    ``xy``, ``height`` of the floor the user stands on (m), ``level`` (index into the building's floors:
    the origin's until the moment of arrival), and per displacement whether it was a step."""

    t: np.ndarray  # (N+1,)
    xy: np.ndarray  # (N+1, 2)
    height: np.ndarray  # (N+1,)
    level: np.ndarray  # (N+1,) int
    is_step: np.ndarray  # (N,) bool
    transitions: tuple[tuple[float, int, int, str], ...]  # (arrival t, from level, to level, way)


def place_links(rng: np.random.Generator, nx: int, ny: int) -> Links:
    """Stairwell, lift and escalator foot on distinct corridor nodes (the escalator's top is a neighbour of
    its foot and none of the others' nodes either)."""
    while True:
        nodes = [(int(rng.integers(0, nx)), int(rng.integers(0, ny))) for _ in range(3)]
        stairs, lift, foot = nodes
        towards = _neighbours(stairs, nx, ny)
        tops = [n for n in _neighbours(foot, nx, ny) if n not in (stairs, lift)]
        if len(set(nodes)) == 3 and tops:
            return Links(
                stairs,
                towards[int(rng.integers(0, len(towards)))],
                lift,
                foot,
                tops[int(rng.integers(0, len(tops)))],
            )


def _neighbours(node: Node, nx: int, ny: int) -> list[Node]:
    i, j = node
    out = [(i + di, j + dj) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))]
    return [n for n in out if 0 <= n[0] < nx and 0 <= n[1] < ny]


class _Path:
    """The samples of a walk as it is built."""

    def __init__(self, xy: np.ndarray, height: float, level: int) -> None:
        self.t = [0.0]
        self.xy = [xy]
        self.height = [height]
        self.level = [level]
        self.is_step: list[bool] = []
        self.pending = [xy]  # the walking polyline not yet cut into steps

    def add(self, dt: float, xy: np.ndarray, height: float, level: int, step: bool) -> None:
        self.t.append(self.t[-1] + dt)
        self.xy.append(xy)
        self.height.append(height)
        self.level.append(level)
        self.is_step.append(step)

    def walk(self, step: float, speed: float) -> None:
        """The pending polyline as steps of ``step`` metres (the last one shorter)."""
        poly = np.array(self.pending)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
        if arc[-1] > 1e-9:
            marks = np.append(np.arange(step, arc[-1] - 0.2 * step, step), arc[-1])  # no sliver of a step
            previous = 0.0
            for s in marks:
                xy = np.array([np.interp(s, arc, poly[:, 0]), np.interp(s, arc, poly[:, 1])])
                self.add((s - previous) / speed, xy, self.height[-1], self.level[-1], True)
                previous = s
        self.pending = [self.xy[-1]]


def storey_walk(
    links: Links,
    nx: int,
    ny: int,
    spacing: float,
    elevations: np.ndarray,
    storeys: dict[str, Any],
    users: dict[str, Any],
    rng: np.random.Generator,
) -> StoreyWalk:
    """A random corridor walk (no U-turns except at dead ends) of ``walk_length_m`` on foot, starting on a
    random floor; at a way between floors the user takes it with ``take_probability``."""
    step, speed, length = users["step_length_m"], users["speed_mps"], users["walk_length_m"]
    n_levels = len(elevations)
    level = int(rng.integers(0, n_levels))
    node: Node = (int(rng.integers(0, nx)), int(rng.integers(0, ny)))
    previous: Node | None = None
    path = _Path(np.array(node, dtype=float) * spacing, float(elevations[level]), level)
    transitions: list[tuple[float, int, int, str]] = []
    walked = 0.0
    arrived = False  # on the landing of a way just taken: the user walks on before taking another

    def at(n: Node) -> np.ndarray:
        return np.array(n, dtype=float) * spacing

    while walked < length:
        ways = [] if arrived else _ways(links, node, level, n_levels)
        arrived = False
        if ways and rng.uniform() < storeys["take_probability"]:
            way = ways[int(rng.integers(0, len(ways)))]
            if way == "lift":
                target = [lv for lv in range(n_levels) if lv != level][int(rng.integers(0, n_levels - 1))]
            else:
                target = level + (1 if way.endswith("up") else -1)
            path.walk(step, speed)
            h0, h1 = float(elevations[level]), float(elevations[target])
            if way.startswith("stairs"):
                st = storeys["stairs"]
                n = max(1, round(st["run_m"] / st["step_length_m"]))
                direction = (at(links.stairs_towards) - at(node)) / spacing
                offsets = [*range(1, n + 1), *range(n - 1, -1, -1)]
                for k, out in enumerate(offsets, start=1):
                    path.add(
                        st["step_period_s"],
                        at(node) + direction * out * st["step_length_m"],
                        h0 + (h1 - h0) * k / len(offsets),
                        target if k == len(offsets) else level,
                        True,
                    )
                walked += len(offsets) * st["step_length_m"]
                previous = None
            elif way == "lift":
                lift = storeys["lift"]
                wait = float(rng.uniform(*lift["wait_s"]))
                path.add(wait, at(node), h0, level, False)
                path.add(abs(h1 - h0) / lift["speed_mps"] + lift["door_s"], at(node), h1, target, False)
                path.add(lift["door_s"], at(node), h1, target, False)
                previous = None
            else:
                esc = storeys["escalator"]
                incline = math.radians(esc["incline_deg"])
                run = abs(h1 - h0) / math.tan(incline)
                ride = abs(h1 - h0) / (esc["speed_mps"] * math.sin(incline))
                foot, top = at(links.escalator_foot), at(links.escalator_top)
                along = (top - foot) / spacing
                # a step on at one end, a step off at the other: the rider faces the way it goes
                low, high = foot + along * step, foot + along * (step + run)
                if way == "escalator up":
                    path.pending.append(low)
                    path.walk(step, speed)
                    path.add(ride, high, h1, target, False)
                    path.pending = [high, top]
                    previous, node = node, links.escalator_top
                else:
                    path.pending.append(high)
                    path.walk(step, speed)
                    path.add(ride, low, h1, target, False)
                    path.pending = [low, foot]
                    previous, node = node, links.escalator_foot
                walked += spacing - run
            transitions.append((path.t[-1] if way != "lift" else path.t[-2], level, target, way.split()[0]))
            level, arrived = target, True
            continue
        choices = [n for n in _neighbours(node, nx, ny) if n != previous] or _neighbours(node, nx, ny)
        previous, node = node, choices[int(rng.integers(0, len(choices)))]
        path.pending.append(at(node))
        walked += spacing
    path.walk(step, speed)
    return StoreyWalk(
        np.array(path.t),
        np.array(path.xy),
        np.array(path.height),
        np.array(path.level, dtype=np.int64),
        np.array(path.is_step, dtype=bool),
        tuple(transitions),
    )


def _ways(links: Links, node: Node, level: int, n_levels: int) -> list[str]:
    """The ways to another floor at this node."""
    up, down = level < n_levels - 1, level > 0
    ways = []
    if node == links.stairs:
        ways += ["stairs up"] * up + ["stairs down"] * down
    if node == links.lift:
        ways.append("lift")
    if node == links.escalator_foot and up:
        ways.append("escalator up")
    if node == links.escalator_top and down:
        ways.append("escalator down")
    return ways


def pressure_at(height_m: np.ndarray, ground_hpa: np.ndarray) -> np.ndarray:
    """The standard atmosphere's pressure ``height_m`` above a ground at ``ground_hpa`` (the inverse of
    ``slam_core.sensing.vertical.pressure_height``)."""
    ground_height = 44_330.77 * (1.0 - (np.asarray(ground_hpa) / SEA_LEVEL_HPA) ** 0.190263)
    out: np.ndarray = SEA_LEVEL_HPA * (1.0 - (ground_height + height_m) / 44_330.77) ** (1.0 / 0.190263)
    return out


def barometer(
    walk: StoreyWalk,
    start_t: float,
    phone_height_m: float,
    weather_hpa_per_s: float,
    params: dict[str, Any],
    rng: np.random.Generator,
) -> np.ndarray:
    """A phone's pressure samples (t_s, hPa) over its walk: the building's ground pressure drifts by
    ``weather_hpa_per_s`` from time 0; the phone adds its own offset and noise."""
    t = np.arange(walk.t[0], walk.t[-1], 1.0 / params["rate_hz"])
    height = np.interp(t, walk.t, walk.height) + phone_height_m
    ground = SEA_LEVEL_HPA + weather_hpa_per_s * (start_t + t)
    offset = rng.normal(0.0, params["offset_sigma_hpa"])
    hpa = pressure_at(height, ground) + offset + rng.normal(0.0, params["noise_sigma_hpa"], t.size)
    return np.column_stack([start_t + t, hpa])
