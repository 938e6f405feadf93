"""PNG figures of ``crowdslam signalslam``: trajectories per method (the paper's Figures 3-6) and WiFi signal
maps from the SignalSLAM trajectories (Figures 9-10)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slam_core.signal_map.graph import Trajectories, position_at

METHODS = (("raw", "PDR"), ("calibrated", "recalibrated PDR (Eq. 4)"), ("graphslam", "GraphSLAM"),
           ("signalslam", "SignalSLAM"))  # fmt: skip
GRID_M = 2.0
BANDWIDTH_M = 3.0
SUPPORT_M = 6.0


def _pyplot() -> Any:
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


def plot_signal_maps(
    folder: Path, prepared: list[Any], trajectories: Trajectories, aps: int = 2
) -> list[Path]:
    """RSS of the most-heard access points on a 2 m grid: Gaussian kernel regression (3 m bandwidth) of the
    scans placed by SignalSLAM; cells with no scan within 6 m are left blank."""
    plt = _pyplot()
    points, columns = [], []
    for p, xy in zip(prepared, trajectories.signalslam, strict=True):
        placed = position_at(p.walk.t_ms, xy, p.scans.t_ms.astype(float))
        for position, entry in zip(placed, p.scans.rss, strict=True):
            points.append(position)
            columns.append(entry)
    if not points:
        return []
    xy = np.array(points)
    heard: dict[int, int] = {}
    for entry in columns:
        for ap in entry:
            heard[ap] = heard.get(ap, 0) + 1
    written = []
    gx = np.arange(xy[:, 0].min(), xy[:, 0].max() + GRID_M, GRID_M)
    gy = np.arange(xy[:, 1].min(), xy[:, 1].max() + GRID_M, GRID_M)
    cells = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    for rank, ap in enumerate(sorted(heard, key=lambda a: -heard[a])[:aps]):
        rows = [i for i, entry in enumerate(columns) if ap in entry]
        rss = np.array([columns[i][ap] for i in rows])
        d2 = np.sum((cells[:, None, :] - xy[rows][None, :, :]) ** 2, axis=-1)
        w = np.exp(-0.5 * d2 / BANDWIDTH_M**2)
        value = np.where(
            d2.min(axis=1) <= SUPPORT_M**2, (w @ rss) / np.maximum(w.sum(axis=1), 1e-12), np.nan
        ).reshape(gy.size, gx.size)
        fig, ax = plt.subplots(figsize=(8, 6), dpi=110)
        image = ax.pcolormesh(gx, gy, value, shading="nearest", cmap="viridis")
        ax.plot(xy[rows, 0], xy[rows, 1], ".", color="white", ms=1.5, alpha=0.5)
        fig.colorbar(image, ax=ax, label="RSS (dBm)")
        ax.set_aspect("equal")
        ax.set_title(f"WiFi AP #{rank + 1} ({heard[ap]} readings): signal map from SignalSLAM trajectories")
        fig.tight_layout()
        path = folder / f"signal_map_ap{rank + 1}.png"
        fig.savefig(path)
        plt.close(fig)
        written.append(path)
    return written
