"""Reader of the Microsoft Indoor Location Competition 2.0 trace format (``FORMAT.md`` beside the data).

Every record type is parsed: the ten documented ones and those found in the files — ``TYPE_BLUE`` (a
generic Bluetooth LE advertiser: name, MAC, RSSI), ``TYPE_BLU4`` (its companion row: two integers and the
same RSSI), ``TYPE_DIST1``/``TYPE_DIST2`` (one row each per walk, three floats, meaning undocumented) and
``TYPE_SENSOR_MAGNETIC_FIELD_ACCURACY_CHANGED``. Lines are not always in time order (the last waypoint is
often repeated after later sensor rows): each stream is sorted by time and exact duplicate times dropped.
A malformed or truncated line raises ``TraceFormatError`` naming the file and the line.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from schemas.floor_plans import FloorPlan, MultiPolygonGeometry, PolygonGeometry

VECTOR_TYPES = {
    "TYPE_ACCELEROMETER": "accelerometer",
    "TYPE_GYROSCOPE": "gyroscope",
    "TYPE_MAGNETIC_FIELD": "magnetometer",
    "TYPE_ROTATION_VECTOR": "rotation_vector",
}
UNCALIBRATED_TYPES = {
    "TYPE_ACCELEROMETER_UNCALIBRATED": "accelerometer_uncalibrated",
    "TYPE_GYROSCOPE_UNCALIBRATED": "gyroscope_uncalibrated",
    "TYPE_MAGNETIC_FIELD_UNCALIBRATED": "magnetometer_uncalibrated",
}
COLUMNS = {
    **dict.fromkeys(VECTOR_TYPES, 6),
    **dict.fromkeys(UNCALIBRATED_TYPES, 9),
    "TYPE_WIFI": 7,
    "TYPE_BEACON": 10,
    "TYPE_WAYPOINT": 4,
    "TYPE_BLUE": 5,
    "TYPE_BLU4": 5,
    "TYPE_DIST1": 5,
    "TYPE_DIST2": 5,
    "TYPE_SENSOR_MAGNETIC_FIELD_ACCURACY_CHANGED": 3,
}


class TraceFormatError(ValueError):
    def __init__(self, path: Path, line: int, message: str) -> None:
        super().__init__(f"{path}:{line}: {message}")
        self.path = path
        self.line = line


@dataclass(frozen=True)
class WifiScan:
    t_ms: int
    ssid: list[str]
    bssid: list[str]
    rssi_dbm: np.ndarray
    frequency_mhz: np.ndarray
    last_seen_ms: np.ndarray


@dataclass
class Trace:
    path: Path
    header: dict[str, str]
    streams: dict[str, np.ndarray] = field(default_factory=dict)
    """name -> (N, 1 + values) arrays: t_ms then the values (accuracy dropped; see ``accuracy``)."""
    accuracy: dict[str, np.ndarray] = field(default_factory=dict)
    wifi: list[WifiScan] = field(default_factory=list)
    beacons: list[tuple[int, str, int, int, int, int, float, str]] = field(default_factory=list)
    """(t_ms, uuid, major, minor, tx_power, rssi, distance, mac)"""
    ble: list[tuple[int, str, str, int]] = field(default_factory=list)
    """TYPE_BLUE rows: (t_ms, name, mac, rssi)"""
    blu4: list[tuple[int, int, int, int]] = field(default_factory=list)
    """TYPE_BLU4 rows: (t_ms, a, b, rssi)"""
    waypoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(K, 3): t_ms, x_m, y_m, sorted by time, duplicates removed"""
    dist1: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    dist2: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    magnetic_accuracy_changes: list[tuple[int, int]] = field(default_factory=list)

    @property
    def start_ms(self) -> int:
        return int(self.header.get("startTime", self.waypoints[0, 0] if len(self.waypoints) else 0))

    @property
    def end_ms(self) -> int:
        return int(self.header.get("endTime", 0))


def _sorted_unique(rows: list[list[float]], width: int) -> np.ndarray:
    if not rows:
        return np.zeros((0, width))
    arr = np.asarray(rows, dtype=float)
    arr = arr[np.argsort(arr[:, 0], kind="stable")]
    keep = np.r_[True, np.diff(arr[:, 0]) > 0]
    return arr[keep]


def read_trace(path: Path) -> Trace:
    path = Path(path)
    header: dict[str, str] = {}
    vectors: dict[str, list[list[float]]] = {}
    accuracy: dict[str, list[list[float]]] = {}
    wifi_rows: dict[int, list[tuple[str, str, int, int, int]]] = {}
    trace = Trace(path=path, header=header)
    waypoints: list[list[float]] = []
    dist1: list[list[float]] = []
    dist2: list[list[float]] = []
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise TraceFormatError(path, 0, f"cannot read: {error}") from error
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        if line.startswith("#"):
            for item in line[1:].strip().split("\t"):
                key, sep, value = item.partition(":")
                if sep:
                    header[key.strip()] = value.strip()
            continue
        parts = line.split("\t")
        kind = parts[1] if len(parts) > 1 else ""
        expected = COLUMNS.get(kind)
        if expected is None:
            raise TraceFormatError(path, number, f"unknown record type {kind!r}")
        if len(parts) != expected:
            raise TraceFormatError(
                path, number, f"{kind} needs {expected} columns, found {len(parts)} (truncated?)"
            )
        try:
            t = int(parts[0])
            if kind in VECTOR_TYPES:
                name = VECTOR_TYPES[kind]
                values = [float(v) for v in parts[2:5]]
                vectors.setdefault(name, []).append([t, *values])
                accuracy.setdefault(name, []).append([t, float(parts[5])])
            elif kind in UNCALIBRATED_TYPES:
                vectors.setdefault(UNCALIBRATED_TYPES[kind], []).append([t, *(float(v) for v in parts[2:8])])
            elif kind == "TYPE_WIFI":
                wifi_rows.setdefault(t, []).append(
                    (parts[2], parts[3].lower(), int(parts[4]), int(parts[5]), int(parts[6]))
                )
            elif kind == "TYPE_BEACON":
                trace.beacons.append(
                    (
                        t,
                        parts[2],
                        int(parts[3]),
                        int(parts[4]),
                        int(parts[5]),
                        int(parts[6]),
                        float(parts[7]),
                        parts[8].upper(),
                    )
                )
            elif kind == "TYPE_WAYPOINT":
                waypoints.append([t, float(parts[2]), float(parts[3])])
            elif kind == "TYPE_BLUE":
                trace.ble.append((t, parts[2], parts[3].upper(), int(parts[4])))
            elif kind == "TYPE_BLU4":
                trace.blu4.append((t, int(parts[2]), int(parts[3]), int(parts[4])))
            elif kind == "TYPE_DIST1":
                dist1.append([t, *(float(v) for v in parts[2:5])])
            elif kind == "TYPE_DIST2":
                dist2.append([t, *(float(v) for v in parts[2:5])])
            else:
                trace.magnetic_accuracy_changes.append((t, int(parts[2])))
        except ValueError as error:
            raise TraceFormatError(path, number, f"bad {kind} value: {error}") from None
    if "startTime" not in header and not vectors and not wifi_rows:
        raise TraceFormatError(path, 0, "no header and no sensor rows: not an Indoor Location 2.0 trace")
    trace.streams = {name: _sorted_unique(rows, len(rows[0])) for name, rows in vectors.items()}
    trace.accuracy = {name: _sorted_unique(rows, 2) for name, rows in accuracy.items()}
    trace.waypoints = _sorted_unique(waypoints, 3)
    trace.dist1 = _sorted_unique(dist1, 4)
    trace.dist2 = _sorted_unique(dist2, 4)
    for t in sorted(wifi_rows):
        strongest: dict[str, tuple[str, str, int, int, int]] = {}
        for row in wifi_rows[t]:  # a BSSID listed twice in one scan: keep its strongest reading
            if row[1] not in strongest or row[2] > strongest[row[1]][2]:
                strongest[row[1]] = row
        rows = list(strongest.values())
        trace.wifi.append(
            WifiScan(
                t_ms=t,
                ssid=[r[0] for r in rows],
                bssid=[r[1] for r in rows],
                rssi_dbm=np.array([r[2] for r in rows], dtype=float),
                frequency_mhz=np.array([r[3] for r in rows], dtype=np.int64),
                last_seen_ms=np.array([r[4] for r in rows], dtype=np.int64),
            )
        )
    trace.beacons.sort(key=lambda b: b[0])
    trace.ble.sort(key=lambda b: b[0])
    return trace


@dataclass(frozen=True)
class FloorInfo:
    width_m: float
    height_m: float
    geojson: dict[str, object]
    image: Path | None
    traces: list[Path]


def read_floor(floor_dir: Path) -> FloorInfo:
    """Floor metadata (``floor_info.json``, ``geojson_map.json``, ``floor_image.png``) and its walks."""
    floor_dir = Path(floor_dir)
    info_path = floor_dir / "floor_info.json"
    try:
        info = json.loads(info_path.read_text())
        width, height = float(info["map_info"]["width"]), float(info["map_info"]["height"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise TraceFormatError(info_path, 0, f"unreadable floor info: {error}") from error
    geo_path = floor_dir / "geojson_map.json"
    try:
        geojson = json.loads(geo_path.read_text()) if geo_path.exists() else {}
    except ValueError as error:
        raise TraceFormatError(geo_path, 0, f"unreadable GeoJSON: {error}") from error
    image = floor_dir / "floor_image.png"
    traces = sorted((floor_dir / "path_data_files").glob("*.txt"))
    return FloorInfo(width, height, geojson, image if image.exists() else None, traces)


@dataclass(frozen=True)
class PlanReading:
    """A floor's map read as a plan, with what of the map could not be used (each counted, never fatal: the
    data set's maps are drawn by many hands, and a plan missing a shop is still a plan)."""

    plan: FloorPlan | None
    skipped_features: int = 0
    """Features with no polygonal geometry (points, lines, a null geometry) or none left after repair."""
    repaired_rings: int = 0
    """Rings that did not end at their first position, closed."""
    dropped_rings: int = 0
    """Rings with fewer than three distinct finite positions, and holes of a dropped outer ring."""


def read_floor_plan(info: FloorInfo) -> PlanReading:
    """The floor's ``geojson_map.json`` as a plan in the local frame: the largest feature (the floor's
    outline) is the walkable area, every other polygon (shops, facilities) an obstacle. The map's WGS-84
    positions are placed by the outline's bounds, which span the floor's width and height (on both shipped
    floors every surveyed waypoint lies inside the outline and none inside a shop). Rings left open are
    closed, positions beyond [x, y] (an altitude) ignored, and degenerate rings and non-polygonal features
    left out and counted. The plan is None without a usable outline."""
    raw: Any = info.geojson
    features = [f for f in raw.get("features", []) if isinstance(f, dict)] if isinstance(raw, dict) else []
    repaired = dropped = 0
    usable: list[tuple[dict[str, Any], list[list[np.ndarray]]]] = []
    for feature in features:
        geometry = feature.get("geometry")
        if not isinstance(geometry, dict):
            continue
        kind, coordinates = geometry.get("type"), geometry.get("coordinates")
        if kind not in ("Polygon", "MultiPolygon") or not isinstance(coordinates, list):
            continue
        polygons = []
        for polygon in [coordinates] if kind == "Polygon" else coordinates:
            rings: list[np.ndarray] = []
            for i, raw_ring in enumerate(polygon if isinstance(polygon, list) else []):
                ring, was_open = _ring_positions(raw_ring)
                if ring is None or (i > 0 and not rings):
                    dropped += 1  # a hole without its outer ring means nothing
                    continue
                repaired += was_open
                rings.append(ring)
            if rings:
                polygons.append(rings)
        if polygons:
            usable.append((feature, polygons))
    skipped = len(features) - len(usable)
    if not usable:
        return PlanReading(None, skipped, repaired, dropped)

    def bounds(polygons: list[list[np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
        every = np.concatenate([ring for rings in polygons for ring in rings])
        return every.min(axis=0), np.ptp(every, axis=0)

    outline = max(usable, key=lambda u: float(np.prod(bounds(u[1])[1])))
    low, span = bounds(outline[1])
    if not (span > 0).all():
        return PlanReading(None, skipped, repaired, dropped)
    scale = np.array([info.width_m, info.height_m]) / span
    out = []
    for feature, polygons in usable:
        kind = "walkable" if feature is outline[0] else "obstacle"
        properties = feature.get("properties")
        name = properties.get("name") if isinstance(properties, dict) else None
        name = name[:128] if isinstance(name, str) and name else None
        geometry = {
            "type": "MultiPolygon",
            "coordinates": [
                [np.round((ring - low) * scale, 3).tolist() for ring in rings] for rings in polygons
            ],
        }
        out.append({"type": "Feature", "geometry": geometry, "properties": {"kind": kind, "name": name}})
    plan = FloorPlan.model_validate({"type": "FeatureCollection", "frame": "local", "features": out})
    return PlanReading(plan, skipped, repaired, dropped)


def _ring_positions(raw: Any) -> tuple[np.ndarray | None, bool]:
    """A GeoJSON ring's finite [x, y] positions, closed, and whether it was open; None when fewer than three
    distinct positions remain."""
    if not isinstance(raw, list):
        return None, False
    points = []
    for position in raw:
        if isinstance(position, list | tuple) and len(position) >= 2:
            try:
                x, y = float(position[0]), float(position[1])
            except (TypeError, ValueError):
                continue
            if math.isfinite(x) and math.isfinite(y):
                points.append((x, y))
    if len(set(points)) < 3:
        return None, False
    was_open = points[0] != points[-1]
    if was_open:
        points.append(points[0])
    return np.array(points, dtype=np.float64), was_open


def floor_level(name: str) -> int | None:
    """The level the data set's floor folder name stands for: ``B1`` is -1, ``F1`` 0, ``F2`` 1, ... (None: not
    a floor's name)."""
    match = re.fullmatch(r"([BF])(\d+)", name)
    if match is None or int(match[2]) == 0:
        return None
    return -int(match[2]) if match[1] == "B" else int(match[2]) - 1


def building_floors(path: Path) -> list[tuple[int, Path]]:
    """The floors of a building folder (its subfolders named as ``floor_level`` reads them, each with its
    walks), lowest first; a floor's own folder is one floor, level 0. ValueError when it is neither."""
    path = Path(path)
    if (path / "path_data_files").is_dir():
        return [(0, path)]
    found = []
    for sub in sorted(p for p in path.iterdir() if p.is_dir()) if path.is_dir() else []:
        level = floor_level(sub.name)
        if level is not None and (sub / "path_data_files").is_dir():
            found.append((level, sub))
    if not found:
        raise ValueError(
            f"{path}: neither a floor (a folder with path_data_files/) nor a building whose subfolders are "
            "floors named B1, F1, F2, ... each with path_data_files/"
        )
    return sorted(found)


def iter_windows(trace: Trace, window_ms: int = 1000, cuts: Sequence[int] = ()) -> Iterator[tuple[int, int]]:
    """Consecutive [start, end) windows covering the trace's sensor data, also split at each time in
    ``cuts`` (so a window ends exactly at, say, a waypoint)."""
    times = [s[:, 0] for s in trace.streams.values() if len(s)]
    times += [np.array([w.t_ms for w in trace.wifi], dtype=float)] if trace.wifi else []
    if not times:
        return
    first = int(min(t.min() for t in times))
    last = int(max(t.max() for t in times))
    for start in range(first, last + 1, window_ms):
        end = start + window_ms
        inner = sorted({int(c) for c in cuts if start < c < end})
        yield from zip([start, *inner], [*inner, end], strict=True)


def shifted(trace: Trace, offset_ms: int) -> Trace:
    """The same walk with every time moved by ``offset_ms`` (replaying walks as if concurrent)."""

    def move(rows: np.ndarray) -> np.ndarray:
        out = rows.copy()
        if len(out):
            out[:, 0] += offset_ms
        return out

    scans = [
        WifiScan(
            s.t_ms + offset_ms,
            s.ssid,
            s.bssid,
            s.rssi_dbm,
            s.frequency_mhz,
            np.where(s.last_seen_ms > 0, s.last_seen_ms + offset_ms, s.last_seen_ms),
        )
        for s in trace.wifi
    ]
    header = dict(trace.header)
    for key in ("startTime", "endTime"):
        if key in header:
            header[key] = str(int(header[key]) + offset_ms)
    return Trace(
        path=trace.path,
        header=header,
        streams={k: move(v) for k, v in trace.streams.items()},
        accuracy=trace.accuracy,
        wifi=scans,
        beacons=[(t + offset_ms, *rest) for t, *rest in trace.beacons],  # type: ignore[misc]
        ble=[(t + offset_ms, *rest) for t, *rest in trace.ble],  # type: ignore[misc]
        blu4=[(t + offset_ms, *rest) for t, *rest in trace.blu4],  # type: ignore[misc]
        waypoints=move(trace.waypoints),
        dist1=trace.dist1,
        dist2=trace.dist2,
        magnetic_accuracy_changes=[(t + offset_ms, a) for t, a in trace.magnetic_accuracy_changes],
    )


def shop_frontages(plan: FloorPlan, reach_m: float) -> list[tuple[str, np.ndarray]]:
    """A zone per shop of the plan (each obstacle polygon), as ``evaluate --zones`` draws them: the shop
    grown by ``reach_m`` on every side (its frontage: the walkable area in front of it, where the surveyed
    walks pass; they never enter a shop, so the shop's own floor inside the zone changes nothing). Named by
    the shop's name, or its number; outlines (K, 2) not closed, simplified to 0.2 m, at most 512 positions.
    Shops whose outline cannot be grown into one simple polygon are left out."""
    import shapely  # deferred: only the evaluation draws zones

    out = []
    for k, feature in enumerate(plan.features):
        g = feature.geometry
        if feature.properties.kind != "obstacle" or not isinstance(g, PolygonGeometry | MultiPolygonGeometry):
            continue
        for rings in [g.coordinates] if isinstance(g, PolygonGeometry) else g.coordinates:
            shop = shapely.make_valid(shapely.Polygon(rings[0]))
            grown = shop.buffer(reach_m, quad_segs=2).simplify(0.2)
            if grown.geom_type != "Polygon" or grown.is_empty:
                continue
            ring = np.asarray(grown.exterior.coords, dtype=np.float64)[:-1]
            if 3 <= len(ring) <= 512:
                out.append((feature.properties.name or f"shop {k}", ring))
    return out
