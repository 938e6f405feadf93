"""Outputs of ``crowdslam signalslam``: trajectories per method (the paper's Figures 3-6), WiFi signal maps
from the SignalSLAM trajectories with their uncertainty (Figures 9-10) as PNG and JSON grids, and the 5 m
fingerprint database."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.signalslam.graph import Trajectories, position_at
from slam_core.signalslam.maps import fingerprint_grid, signal_grid
from slam_core.signalslam.windows import rss_matrix

METHODS = (("raw", "PDR"), ("calibrated", "recalibrated PDR (Eq. 4)"), ("graphslam", "GraphSLAM"),
           ("signalslam", "SignalSLAM"))  # fmt: skip
GRID_M = 2.0
BANDWIDTH_M = 3.0
SUPPORT_M = 6.0


def _pyplot() -> Any:
    # deferred: matplotlib loads only when plotting, its backend chosen before pyplot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectories(
    folder: Path, prepared: list[Any], trajectories: Trajectories, walks: int = 8
) -> list[Path]:
    """The longest walks under each method, with their surveyed waypoints."""
    plt = _pyplot()
    order = np.argsort([-p.walk.lengths.sum() for p in prepared])[:walks]
    fig, axes = plt.subplots(2, 2, figsize=(11, 9), dpi=110, sharex=True, sharey=True)
    for ax, (name, title) in zip(axes.ravel(), METHODS, strict=True):
        for colour, i in enumerate(order):
            xy = getattr(trajectories, name)[i]
            ax.plot(xy[:, 0], xy[:, 1], color=f"C{colour}", lw=1.2)
            wp = prepared[i].waypoints
            ax.plot(wp[:, 1], wp[:, 2], "o", color=f"C{colour}", ms=3, alpha=0.7)
        ax.set_title(title)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    fig.suptitle("estimated trajectories (lines) and surveyed waypoints (dots)")
    fig.tight_layout()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "trajectories.png"
    fig.savefig(path)
    plt.close(fig)
    return [path]


def _placed_scans(run: Any) -> tuple[np.ndarray, np.ndarray]:
    """Every scan placed by SignalSLAM, and its RSS row over the floor's AP columns (NaN = not heard)."""
    n_aps = len(run.ap_names)
    points = [position_at(p.walk.t_ms, xy, p.scans.t_ms.astype(float))
              for p, xy in zip(run.prepared, run.trajectories.signalslam, strict=True)]  # fmt: skip
    rows = [rss_matrix(p.scans.rss, n_aps) for p in run.prepared]
    return np.vstack([np.zeros((0, 2)), *points]), np.vstack([np.zeros((0, n_aps)), *rows])


def write_maps(folder: Path, run: Any, aps: int = 2) -> list[Path]:
    """Signal maps of the most-heard APs and of the magnetic magnitude (PNG heatmap of the mean, PNG of its
    uncertainty, JSON grid) and the 5 m fingerprint database (JSON), all from the SignalSLAM trajectories."""
    xy, rss = _placed_scans(run)
    written = write_scan_maps(folder, xy, rss, run.ap_names, aps)
    points, values = [np.zeros((0, 2))], [np.zeros((0, 1))]
    for p, placed in zip(run.prepared, run.trajectories.signalslam, strict=True):
        magnitude = p.walk.window_magnetic
        if magnitude is not None:
            has = np.isfinite(magnitude)
            points.append(position_at(p.walk.t_ms, placed, p.walk.window_t[has].astype(float)))
            values.append(magnitude[has, None])
    return written + write_column_maps(
        folder, np.vstack(points), np.vstack(values), ["magnetic magnitude"], MAGNETIC, 1
    )


@dataclass(frozen=True)
class MapKind:
    """How one kind of signal's maps are named and labelled."""

    prefix: str  # files: signal_map_<prefix><rank>.png / .json / .geojson
    id_key: str  # the column's identity in the JSON and GeoJSON
    value_key: str  # the mean's key: a unit-suffixed name
    spread_key: str
    label: str  # the colour bar's label
    unit: str
    title: str  # the map's title, with {name}


AP = MapKind("ap", "bssid", "mean_dbm", "std_db", "RSS (dBm)", "dB", "AP {name}")
LTE_CELL = MapKind("cell", "cell_id", "mean_dbm", "std_db", "RSRP (dBm)", "dB", "LTE cell {name}")
MAGNETIC = MapKind("magnetic", "field", "mean_ut", "std_ut", "magnitude (uT)", "uT", "{name}")


def write_column_maps(
    folder: Path,
    xy: np.ndarray,
    values: np.ndarray,
    names: list[str],
    kind: MapKind,
    count: int = 2,
    to_wgs84: Callable[[float, float], tuple[float, float]] | None = None,
) -> list[Path]:
    """Signal maps of the ``count`` most-read columns of ``values`` (S, C; NaN = no reading) at positions
    (S, 2): a PNG of the mean and of its uncertainty, a JSON grid, and with ``to_wgs84`` (the building's
    geo-reference) a GeoJSON of one WGS-84 point per mapped cell with its mean, spread and effective
    number of readings."""
    plt = _pyplot()
    if xy.shape[0] == 0 or values.shape[1] == 0:
        return []
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    heard = np.isfinite(values).sum(axis=0)
    pad = BANDWIDTH_M  # the map reaches a little around the readings (and a corridor is not a line)
    bounds = (xy[:, 0].min() - pad, xy[:, 1].min() - pad, xy[:, 0].max() + pad, xy[:, 1].max() + pad)
    for rank, column in enumerate(np.argsort(-heard, kind="stable")[:count]):
        rows = np.isfinite(values[:, column])
        if not rows.any():
            break
        grid = signal_grid(xy[rows], values[rows, column], GRID_M, BANDWIDTH_M, SUPPORT_M, bounds)
        gx, gy = grid.centres()
        name = names[column]
        fig, (ax_mean, ax_std) = plt.subplots(1, 2, figsize=(13, 5.5), dpi=110, sharey=True)
        for ax, field, label in (
            (ax_mean, grid.mean, kind.label),
            (ax_std, grid.std, f"spread ({kind.unit})"),
        ):
            image = ax.pcolormesh(gx, gy, field, shading="nearest", cmap="viridis")
            fig.colorbar(image, ax=ax, label=label)
            ax.set_aspect("equal")
        ax_mean.plot(xy[rows, 0], xy[rows, 1], ".", color="white", ms=1.2, alpha=0.5)
        ax_mean.set_title(
            f"{kind.title.format(name=name)}: {int(heard[column])} readings placed by SignalSLAM"
        )
        ax_std.set_title("uncertainty: kernel-weighted spread of the readings")
        fig.tight_layout()
        stem = f"signal_map_{kind.prefix}{rank + 1}"
        png = folder / f"{stem}.png"
        fig.savefig(png)
        plt.close(fig)
        grid_json = folder / f"{stem}.json"
        grid_json.write_text(json.dumps({
            kind.id_key: name, "origin_m": grid.origin.tolist(), "cell_m": grid.cell_m,
            kind.value_key: _nullable(grid.mean), kind.spread_key: _nullable(grid.std),
            "effective_readings": _nullable(grid.effective_n),
        }))  # fmt: skip
        written += [png, grid_json]
        if to_wgs84 is not None:
            geojson = folder / f"{stem}.geojson"
            geojson.write_text(json.dumps(_grid_geojson(grid, name, kind, to_wgs84)))
            written.append(geojson)
    return written


def write_scan_maps(
    folder: Path,
    xy: np.ndarray,
    rss: np.ndarray,
    ap_names: list[str],
    aps: int = 2,
    to_wgs84: Callable[[float, float], tuple[float, float]] | None = None,
) -> list[Path]:
    """WiFi maps of the ``aps`` most-heard APs from placed scans (positions (S, 2), RSS rows over
    ``ap_names``, NaN = not heard; ``write_column_maps``) and the 5 m fingerprint database (JSON)."""
    if xy.shape[0] == 0:
        return []
    written = write_column_maps(folder, xy, rss, ap_names, AP, aps, to_wgs84)
    database = fingerprint_grid(xy, rss, 5.0)
    cells = [
        {
            "x_m": float(x), "y_m": float(y), "scans": int(n),
            "rss_dbm": {ap_names[a]: round(float(v), 1) for a, v in enumerate(row) if np.isfinite(v)},
        }
        for (x, y), row, n in zip(database.xy, database.rss, database.scans, strict=True)
    ]  # fmt: skip
    db_path = folder / "fingerprints_5m.json"
    db_path.write_text(json.dumps({"cell_m": 5.0, "cells": cells}))
    written.append(db_path)
    return written


def _grid_geojson(
    grid: Any, name: str, kind: MapKind, to_wgs84: Callable[[float, float], tuple[float, float]]
) -> dict[str, Any]:
    gx, gy = grid.centres()
    features = []
    for iy, y in enumerate(gy):
        for ix, x in enumerate(gx):
            if not np.isfinite(grid.mean[iy, ix]):
                continue
            lat, lon = to_wgs84(float(x), float(y))
            features.append({
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [round(lon, 8), round(lat, 8)]},
                "properties": {kind.id_key: name, kind.value_key: round(float(grid.mean[iy, ix]), 2),
                               kind.spread_key: round(float(grid.std[iy, ix]), 2),
                               "effective_readings": round(float(grid.effective_n[iy, ix]), 2)},
            })  # fmt: skip
    return {"type": "FeatureCollection", "features": features}


def _nullable(grid: np.ndarray) -> list[list[float | None]]:
    return [[None if not np.isfinite(v) else round(float(v), 2) for v in row] for row in grid]
