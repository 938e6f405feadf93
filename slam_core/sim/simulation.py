"""Simulate a scenario exactly as given (the paper testbed: ``server/data/paper-testbed.json``).

Produces what phones would send (PDR steps with the scenario's noise model, WiFi scans with path loss, walls
and correlated shadowing, Bluetooth RSS between phones, building-anchor detections with confused types,
start fixes) plus the ground truth. Nothing here is tuned to the filter: every number comes from the
scenario dict; the seed picks the world and the walks. The caller loads the JSON (slam_core does no I/O).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter

from slam_core.filter.params import ANCHOR_TYPES
from slam_core.sim.storeys import Links, StoreyWalk, barometer, place_links, storey_walk


@dataclass(frozen=True)
class Scenario:
    raw: dict[str, Any]

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> Scenario:
        for section in ("floor", "building_anchors", "users", "pdr_noise", "wifi", "bluetooth"):
            if section not in raw:
                raise ValueError(f"scenario lacks the '{section}' section")
        if raw["floor"].get("corridors") != "grid":
            raise ValueError("only 'grid' corridor layouts are supported")
        types = raw["building_anchors"]["types"]
        if tuple(types) != ANCHOR_TYPES[: len(types)]:
            raise ValueError(f"anchor types must be a prefix of {ANCHOR_TYPES}")
        confusion = np.asarray(raw["building_anchors"]["type_confusion"], dtype=float)
        if confusion.shape != (len(types), len(types)) or not np.allclose(confusion.sum(axis=1), 1.0):
            raise ValueError("type_confusion must be square over the types with rows summing to 1")
        storeys = raw.get("storeys")
        if storeys is not None:
            elevations = np.asarray(storeys.get("elevations_m", []), dtype=float)
            if elevations.size < 2 or np.any(np.diff(elevations) <= 0):
                raise ValueError("storeys.elevations_m: at least two floors, each above the one below")
            if (
                not 0.0 <= storeys["take_probability"] <= 1.0
                or not 0.0 <= storeys["barometer"]["share"] <= 1.0
            ):
                raise ValueError("storeys: take_probability and barometer.share must be in [0, 1]")
        return cls(raw)

    def __getitem__(self, key: str) -> Any:
        return self.raw[key]

    def with_setting(self, section: str, key: str, value: Any) -> Scenario:
        """The scenario with one setting changed (a copy: this scenario stays as it is)."""
        raw = {k: dict(v) if isinstance(v, dict) else v for k, v in self.raw.items()}
        if section not in raw or not isinstance(raw[section], dict):
            raise KeyError(f"scenario has no section {section!r}")
        raw[section][key] = value
        return Scenario.from_dict(raw)


@dataclass(frozen=True)
class World:
    width: float
    height: float
    spacing: float
    corridor_half_width: float
    anchor_xy: np.ndarray  # (A, 2)
    anchor_type: np.ndarray  # (A,)
    anchor_known: np.ndarray  # (A,) bool
    ap_xy: np.ndarray  # (P, 2)
    shadow: np.ndarray  # (L x P, H, W) dB on a 1 m grid: AP p seen from floor l at [l * P + p]
    elevations: np.ndarray = field(default_factory=lambda: np.zeros(1))  # (L,) floor heights (m)
    anchor_level: np.ndarray | None = None  # (A,) floor index; None: all on the one floor
    ap_level: np.ndarray | None = None  # (P,)
    links: Links | None = None  # the ways between floors (``slam_core.sim.storeys``)
    weather_hpa_per_s: float = 0.0
    floor_loss_db: float = 0.0  # per floor between a transmitter and a receiver
    phone_height_m: float = 0.0  # above the floor the user stands on

    @property
    def levels(self) -> int:
        return int(self.elevations.size)

    def anchor_levels(self) -> np.ndarray:
        n = self.anchor_xy.shape[0]
        return np.zeros(n, dtype=np.int64) if self.anchor_level is None else self.anchor_level


@dataclass(frozen=True)
class UserTrace:
    start_t: float
    t: np.ndarray  # (S+1,) time of each position (index 0 = start)
    xy: np.ndarray  # (S+1, 2) true positions
    step_length_obs: np.ndarray  # (S,)
    step_heading_obs: np.ndarray  # (S,) rad counter-clockwise from east (phone azimuth converted)
    start_fix: np.ndarray  # (2,)
    start_heading_fix: float
    anchor_step: np.ndarray  # (D,) index of the step at which a detection happens (position index)
    anchor_true: np.ndarray  # (D,) true anchor index
    anchor_detected_type: np.ndarray  # (D,)
    scan_t: np.ndarray  # (C,)
    scan_rss: np.ndarray  # (C, P) dBm, NaN where not heard
    anchor_passes: int  # passes within the detection radius, detected or not
    is_step: np.ndarray | None = None  # (S,) whether each displacement was a step (None: all were)
    level: np.ndarray | None = None  # (S+1,) floor index at each position (None: all on the one floor)
    transitions: tuple[tuple[float, int, int, str], ...] = ()  # (arrival t, from, to, way)
    pressure: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 2))
    )  # (K, 2) t_s, hPa; none: no barometer
    way_detections: tuple[tuple[int, int, float], ...] = ()
    """A phone without a barometer: (position index, type, rise or NaN) of the ways its detectors found."""

    def level_at(self, t: float) -> int:
        """The floor index at time ``t`` (the origin's until the moment of arrival)."""
        return _level_at(self.t, self.level, t)


def _level_at(t: np.ndarray, level: np.ndarray | None, at: float) -> int:
    """The floor index at time ``at`` of positions at times ``t`` on floors ``level`` (None: floor 0)."""
    if level is None:
        return 0
    return int(level[max(int(np.searchsorted(t, at, side="right")) - 1, 0)])


@dataclass(frozen=True)
class Simulation:
    scenario: Scenario
    world: World
    users: list[UserTrace]
    bt_t: np.ndarray  # (B,) times of Bluetooth sightings
    bt_pair: np.ndarray  # (B, 2) user indices (receiver, sender)
    bt_rss: np.ndarray  # (B,)
    anchors_passed_per_user: float

    def true_level(self, user: int, t: float) -> int:
        return self.users[user].level_at(t)

    def true_position(self, user: int, t: float) -> np.ndarray:
        trace = self.users[user]
        return np.array([np.interp(t, trace.t, trace.xy[:, 0]), np.interp(t, trace.t, trace.xy[:, 1])])


# ----------------------------------------------------------------------------- world
def _grid_lines(length: float, spacing: float) -> np.ndarray:
    return np.arange(0.0, length + 1e-9, spacing)


def _point_on_corridors(rng: np.random.Generator, width: float, height: float, spacing: float) -> np.ndarray:
    xs, ys = _grid_lines(width, spacing), _grid_lines(height, spacing)
    horizontal = len(ys) * width
    vertical = len(xs) * height
    if rng.uniform() < horizontal / (horizontal + vertical):
        return np.array([rng.uniform(0, width), rng.choice(ys)])
    return np.array([rng.choice(xs), rng.uniform(0, height)])


def build_world(scenario: Scenario, rng: np.random.Generator) -> World:
    if "storeys" in scenario.raw:
        return _storey_world(scenario, rng)
    floor, anchors, wifi = scenario["floor"], scenario["building_anchors"], scenario["wifi"]
    width, height, spacing = floor["width_m"], floor["height_m"], floor["corridor_spacing_m"]
    min_gap = 5.0  # "on corridors, at least 5 m apart"
    points: list[np.ndarray] = []
    while len(points) < anchors["count"]:
        p = _point_on_corridors(rng, width, height, spacing)
        if all(np.linalg.norm(p - q) >= min_gap for q in points):
            points.append(p)
    n_types = len(anchors["types"])
    anchor_type = rng.integers(0, n_types, anchors["count"])
    known = np.zeros(anchors["count"], dtype=bool)
    known[: anchors["known_positions"]] = True
    n_ap = wifi["access_points"]
    ap_xy = np.column_stack([rng.uniform(0, width, n_ap), rng.uniform(0, height, n_ap)])
    shadow = _shadowing(rng, n_ap, width, height, wifi)
    return World(
        width,
        height,
        spacing,
        floor["corridor_width_m"] / 2.0,
        np.array(points),
        anchor_type,
        known,
        ap_xy,
        shadow,
    )


def _shadowing(
    rng: np.random.Generator, n: int, width: float, height: float, wifi: dict[str, Any]
) -> np.ndarray:
    """``n`` correlated shadowing fields (dB) on a 1 m grid: white noise smoothed to the correlation length,
    rescaled to sigma."""
    gw, gh = math.ceil(width) + 1, math.ceil(height) + 1
    shadow = np.empty((n, gh, gw))
    for k in range(n):
        grid = gaussian_filter(rng.standard_normal((gh, gw)), sigma=wifi["shadowing_correlation_m"] / 2.0)
        shadow[k] = grid / grid.std() * wifi["shadowing_sigma_db"]
    return shadow


def _storey_world(scenario: Scenario, rng: np.random.Generator) -> World:
    """Every floor the scenario's floor, with its own anchors (``count`` each, the first ``known_positions``
    of each known) and access points, the ways between floors, and the weather's drift."""
    floor, anchors, wifi, storeys = (
        scenario["floor"],
        scenario["building_anchors"],
        scenario["wifi"],
        scenario["storeys"],
    )
    width, height, spacing = floor["width_m"], floor["height_m"], floor["corridor_spacing_m"]
    elevations = np.asarray(storeys["elevations_m"], dtype=float)
    n_levels, n_ap = elevations.size, wifi["access_points"]
    points: list[np.ndarray] = []
    levels: list[int] = []
    known: list[bool] = []
    for level in range(n_levels):
        mine: list[np.ndarray] = []
        while len(mine) < anchors["count"]:
            p = _point_on_corridors(rng, width, height, spacing)
            if all(np.linalg.norm(p - q) >= 5.0 for q in mine):
                mine.append(p)
        points += mine
        levels += [level] * len(mine)
        known += [k < anchors["known_positions"] for k in range(len(mine))]
    anchor_type = rng.integers(0, len(anchors["types"]), len(points))
    ap_xy = np.column_stack([rng.uniform(0, width, n_ap * n_levels), rng.uniform(0, height, n_ap * n_levels)])
    ap_level = np.repeat(np.arange(n_levels), n_ap)
    shadow = _shadowing(rng, n_levels * ap_xy.shape[0], width, height, wifi)
    nx, ny = round(width / spacing) + 1, round(height / spacing) + 1
    links = place_links(rng, nx, ny)
    weather = float(rng.choice([-1.0, 1.0])) * storeys["barometer"]["weather_drift_hpa_per_hour"] / 3600.0
    return World(
        width,
        height,
        spacing,
        floor["corridor_width_m"] / 2.0,
        np.array(points),
        anchor_type,
        np.array(known),
        ap_xy,
        shadow,
        elevations,
        np.array(levels, dtype=np.int64),
        ap_level,
        links,
        weather,
        storeys["floor_loss_db"],
        storeys["phone_height_m"],
    )


FRONTAGE_M = 4.0
"""A room's or shop's zone reaches this far out of it: the walkable area in front of it, where people pass
(``evaluate --zones``)."""


def room_zones(world: World, reach_m: float = FRONTAGE_M) -> tuple[list[str], list[np.ndarray], list[int]]:
    """A zone per room of the world on every floor, as ``evaluate --zones`` draws them: the room (the block
    between four corridors) grown by ``reach_m`` on every side, so it holds the corridors in front of it,
    which is where the walks go (no walk enters a room). Ids ``L<floor>-<column>-<row>``; outlines (4, 2)."""
    hw = world.corridor_half_width
    xs, ys = _grid_lines(world.width, world.spacing), _grid_lines(world.height, world.spacing)
    ids, rings, levels = [], [], []
    for level in range(world.levels):
        for i, (x0, x1) in enumerate(itertools.pairwise(xs)):
            for j, (y0, y1) in enumerate(itertools.pairwise(ys)):
                a, b = x0 + hw - reach_m, x1 - hw + reach_m
                c, d = y0 + hw - reach_m, y1 - hw + reach_m
                ids.append(f"L{level}-{i}-{j}")
                rings.append(np.array([[a, c], [b, c], [b, d], [a, d]]))
                levels.append(level)
    return ids, rings, levels


def count_walls(world: World, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Walls crossed on segments a[i] -> b[i]: room walls run along every corridor edge, open where another
    corridor crosses it."""
    a = np.atleast_2d(a)
    b = np.atleast_2d(b)
    total = np.zeros(max(len(a), len(b)))
    hw, sp = world.corridor_half_width, world.spacing
    for axis, length in ((0, world.width), (1, world.height)):
        other = 1 - axis
        for centre in _grid_lines(length, sp):
            for edge in (centre - hw, centre + hw):
                if edge <= 0 or edge >= length:
                    continue
                da = a[:, axis] - edge
                db = b[:, axis] - edge
                crosses = da * db < 0
                frac = np.where(crosses, da / np.where(crosses, da - db, 1.0), 0.0)
                cross_other = a[:, other] + frac * (b[:, other] - a[:, other])
                in_corridor = np.abs(cross_other - np.round(cross_other / sp) * sp) <= hw
                total += crosses & ~in_corridor
    return total


def wifi_rss(
    world: World, wifi: dict[str, Any], xy: np.ndarray, rng: np.random.Generator, level: int = 0
) -> np.ndarray:
    """One scan's RSS per AP at ``xy`` on floor index ``level`` (NaN below the sensitivity). Across floors,
    the distance is the 3D one and each floor between costs the scenario's ``storeys.floor_loss_db``."""
    d_floor = np.linalg.norm(world.ap_xy - xy, axis=1)
    if world.ap_level is None:
        d = np.sqrt(d_floor**2 + 9.0)  # APs 3 m above the floor
        floors_between = np.zeros(d.size)
        floor_loss = 0.0
        shadows = world.shadow
    else:
        phone = world.elevations[level] + world.phone_height_m
        dz = world.elevations[world.ap_level] + 3.0 - phone
        d = np.sqrt(d_floor**2 + dz**2)
        floors_between = np.abs(world.ap_level - level).astype(float)
        floor_loss = world.floor_loss_db
        n_ap = world.ap_xy.shape[0]
        shadows = world.shadow[level * n_ap : (level + 1) * n_ap]
    walls = count_walls(world, world.ap_xy, np.broadcast_to(xy, world.ap_xy.shape))
    gx = min(max(xy[0], 0.0), shadows.shape[2] - 1.001)
    gy = min(max(xy[1], 0.0), shadows.shape[1] - 1.001)
    ix, iy = int(gx), int(gy)
    fx, fy = gx - ix, gy - iy
    s = shadows
    shadow = (
        s[:, iy, ix] * (1 - fx) * (1 - fy)
        + s[:, iy, ix + 1] * fx * (1 - fy)
        + s[:, iy + 1, ix] * (1 - fx) * fy
        + s[:, iy + 1, ix + 1] * fx * fy
    )
    rss = (
        wifi["tx_power_dbm_at_1m"]
        - 10.0 * wifi["path_loss_exponent"] * np.log10(d)
        - wifi["wall_loss_db_per_wall"] * walls
        - floor_loss * floors_between
        + shadow
        + rng.normal(0.0, wifi["scan_noise_sigma_db"], len(d))
    )
    heard: np.ndarray = np.where(rss < wifi["sensitivity_dbm"], np.nan, np.minimum(rss, 0.0))
    return heard


# ----------------------------------------------------------------------------- walks
def _corridor_walk(world: World, rng: np.random.Generator, length: float, step: float) -> np.ndarray:
    """Positions every ``step`` metres along a random corridor walk: no U-turns except at dead ends."""
    nx = round(world.width / world.spacing) + 1
    ny = round(world.height / world.spacing) + 1
    node = (int(rng.integers(0, nx)), int(rng.integers(0, ny)))
    previous: tuple[int, int] | None = None
    vertices = [np.array(node, dtype=float) * world.spacing]
    walked = 0.0
    while walked < length + step:
        i, j = node
        neighbours = [(i + di, j + dj) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        neighbours = [n for n in neighbours if 0 <= n[0] < nx and 0 <= n[1] < ny]
        choices = [n for n in neighbours if n != previous] or neighbours
        nxt = choices[int(rng.integers(0, len(choices)))]
        previous, node = node, nxt
        vertices.append(np.array(node, dtype=float) * world.spacing)
        walked += world.spacing
    poly = np.array(vertices)
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, length + 1e-9, step)
    return np.column_stack([np.interp(s, arc, poly[:, 0]), np.interp(s, arc, poly[:, 1])])


def _user_trace(scenario: Scenario, world: World, rng: np.random.Generator) -> UserTrace:
    users, noise, anchors, wifi = (
        scenario["users"],
        scenario["pdr_noise"],
        scenario["building_anchors"],
        scenario["wifi"],
    )
    step = users["step_length_m"]
    storeys: StoreyWalk | None = None
    if world.links is None:
        period = step / users["speed_mps"]
        xy = _corridor_walk(world, rng, users["walk_length_m"], step)
        start_t = float(rng.uniform(0.0, 30.0))  # "all users start within the first 30 s"
        t = start_t + period * np.arange(len(xy))
    else:
        nx, ny = round(world.width / world.spacing) + 1, round(world.height / world.spacing) + 1
        storeys = storey_walk(
            world.links, nx, ny, world.spacing, world.elevations, scenario["storeys"], users, rng
        )
        start_t = float(rng.uniform(0.0, 30.0))
        xy, t = storeys.xy, start_t + storeys.t
    d = np.diff(xy, axis=0)
    true_len = np.linalg.norm(d, axis=1)
    true_heading = np.arctan2(d[:, 1], d[:, 0])
    n = len(d)
    scale_err = rng.normal(0.0, noise["step_length_scale_sigma"])
    length_obs = np.maximum(
        true_len * (1.0 + scale_err) + rng.normal(0.0, noise["step_length_sigma_m"], n), 0.05
    )
    bias = math.radians(rng.normal(0.0, noise["heading_bias_sigma_deg"]))
    walk = np.cumsum(rng.normal(0.0, math.radians(noise["heading_random_walk_deg_per_sqrt_step"]), n))
    white = rng.normal(0.0, math.radians(noise["heading_change_sigma_deg"]), n)
    heading_obs = (true_heading + bias + walk + white + math.pi) % (2 * math.pi) - math.pi
    start_fix = xy[0] + rng.normal(0.0, users["start_fix_sigma_m"], 2)
    first = int(np.argmax(true_len > 0))  # the first move (a lift may come before it)
    start_heading = float(
        true_heading[first] + math.radians(rng.normal(0.0, users["start_heading_sigma_deg"]))
    )
    # building anchors: one detection per pass within the radius, at the closest step, with probability p
    radius, p_detect = anchors["detection_radius_m"], anchors["detection_probability"]
    confusion = np.asarray(anchors["type_confusion"])
    det_step, det_true, det_type = [], [], []
    passes = 0
    dist = np.linalg.norm(xy[:, None, :] - world.anchor_xy[None, :, :], axis=2)  # (S+1, A)
    if storeys is not None:  # an anchor is passed on its own floor only
        dist[storeys.level[:, None] != world.anchor_levels()[None, :]] = np.inf
    for a in range(world.anchor_xy.shape[0]):
        inside = dist[:, a] <= radius
        k = 0
        while k < len(inside):
            if inside[k]:
                end = k
                while end + 1 < len(inside) and inside[end + 1]:
                    end += 1
                passes += 1
                if rng.uniform() < p_detect:
                    closest = k + int(np.argmin(dist[k : end + 1, a]))
                    det_step.append(max(closest, 1))
                    det_true.append(a)
                    det_type.append(int(rng.choice(len(confusion), p=confusion[world.anchor_type[a]])))
                k = end + 1
            else:
                k += 1
    order = np.argsort(det_step, kind="stable")
    # WiFi scans every scan_period with a random phase
    scan_t = np.arange(start_t + rng.uniform(0, wifi["scan_period_s"]), t[-1], wifi["scan_period_s"])
    level = storeys.level if storeys is not None else None
    scan_rss = np.array(
        [
            wifi_rss(
                world,
                wifi,
                np.array([np.interp(ts, t, xy[:, 0]), np.interp(ts, t, xy[:, 1])]),
                rng,
                _level_at(t, level, ts),
            )
            for ts in scan_t
        ]
    ).reshape(len(scan_t), world.ap_xy.shape[0])
    pressure = np.zeros((0, 2))
    ways: list[tuple[int, int, float]] = []
    if storeys is not None and rng.uniform() < scenario["storeys"]["barometer"]["share"]:
        pressure = barometer(
            storeys,
            start_t,
            world.phone_height_m,
            world.weather_hpa_per_s,
            scenario["storeys"]["barometer"],
            rng,
        )
    elif storeys is not None:  # the phone's own detectors, from its accelerometer
        share = scenario["storeys"]["accelerometer"]["lift_rise_sigma_share"]
        for arrival, was, now, way in storeys.transitions:
            if way == "escalator" or rng.uniform() >= p_detect:
                continue
            k = int(np.searchsorted(storeys.t, arrival))
            rise = world.elevations[now] - world.elevations[was]
            if way == "lift":
                ways.append((k, ANCHOR_TYPES.index("elevator"), float(rise * (1.0 + rng.normal(0.0, share)))))
            else:
                stairs = ANCHOR_TYPES.index("stairs")
                ways.append((k, int(rng.choice(len(confusion), p=confusion[stairs])), math.nan))
    return UserTrace(
        start_t,
        t,
        xy,
        length_obs,
        heading_obs,
        start_fix,
        start_heading,
        np.asarray(det_step, dtype=np.int64)[order],
        np.asarray(det_true, dtype=np.int64)[order],
        np.asarray(det_type, dtype=np.int64)[order],
        scan_t,
        scan_rss,
        passes,
        None if storeys is None else storeys.is_step,
        level,
        () if storeys is None else tuple((start_t + a, f, to, w) for a, f, to, w in storeys.transitions),
        pressure,
        tuple(ways),
    )


def _bluetooth(
    scenario: Scenario, world: World, traces: list[UserTrace], rng: np.random.Generator
) -> tuple[np.ndarray, ...]:
    """Every pair's sightings each period; across floors, the 3D distance and the floors' loss."""
    bt = scenario["bluetooth"]
    t_end = max(tr.t[-1] for tr in traces)
    times, pairs, rss = [], [], []
    for ts in np.arange(0.0, t_end, bt["period_s"]):
        active = [i for i, tr in enumerate(traces) if tr.t[0] <= ts <= tr.t[-1]]
        pos = {
            i: np.array(
                [
                    np.interp(ts, traces[i].t, traces[i].xy[:, 0]),
                    np.interp(ts, traces[i].t, traces[i].xy[:, 1]),
                ]
            )
            for i in active
        }
        for ii, i in enumerate(active):
            for j in active[ii + 1 :]:
                d = max(float(np.linalg.norm(pos[i] - pos[j])), 0.1)
                loss = 0.0
                if world.links is not None:
                    li, lj = traces[i].level_at(ts), traces[j].level_at(ts)
                    d = math.hypot(d, world.elevations[li] - world.elevations[lj])
                    loss = world.floor_loss_db * abs(li - lj)
                for rx, tx in ((i, j), (j, i)):
                    r = (
                        bt["rss_at_1m_dbm"]
                        - 10 * bt["path_loss_exponent"] * math.log10(d)
                        - loss
                        + rng.normal(0, bt["noise_sigma_db"])
                    )
                    if r >= bt["sensitivity_dbm"]:
                        times.append(ts)
                        pairs.append((rx, tx))
                        rss.append(min(r, 0.0))
    return np.array(times), np.array(pairs, dtype=np.int64).reshape(-1, 2), np.array(rss)


def simulate(scenario: Scenario, seed: int, world_seed: int | None = None) -> Simulation:
    """The scenario's world and its users' walks from ``seed``; with ``world_seed``, the world (anchors,
    access points, shadowing) from that seed instead, so that several crowds walk the same building."""
    rng = np.random.default_rng(seed)
    world = build_world(scenario, rng if world_seed is None else np.random.default_rng(world_seed))
    traces = [_user_trace(scenario, world, rng) for _ in range(scenario["users"]["count"])]
    bt_t, bt_pair, bt_rss = _bluetooth(scenario, world, traces, rng)
    passed = float(np.mean([tr.anchor_passes for tr in traces]))
    return Simulation(scenario, world, traces, bt_t, bt_pair, bt_rss, passed)
