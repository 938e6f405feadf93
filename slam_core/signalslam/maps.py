"""Signal maps from placed measurements, the fingerprint database and WiFi localisation on it
(SignalSLAM Section IV: dense maps per access point; localisation with the maps built while walking).

- ``signal_grid``: Nadaraya-Watson (Gaussian kernel) regression of one signal on a regular grid, with its
  uncertainty: the kernel-weighted spread of the readings around the mean, and the effective number of
  readings (sum w)^2 / sum w^2 behind each cell. Cells with no reading within ``support_m`` are NaN.
- ``fingerprint_grid``: every reading of a scan binned into ``cell_m`` cells; per cell the mean RSS of each AP
  (NaN where the AP was never heard there) and how often each AP was heard (its visibility).
- ``localise_knn``: weighted kNN (weights 1/d) over the union-fingerprint distance (``slam_core.wifi.pairs``).
- ``localise_kernel``: kernel regression with the KL kernel on AP visibility (Eq. 7 in signal space): the
  kernel-weighted mean of the ``n`` most similar cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_core.signalslam.similarity import kl_kernel, visibility_multinomials
from slam_core.wifi.pairs import fingerprint_matrix


@dataclass(frozen=True)
class SignalGrid:
    origin: np.ndarray  # (2,) centre of cell [0, 0]
    cell_m: float
    mean: np.ndarray  # (ny, nx); NaN outside the support
    std: np.ndarray  # (ny, nx)
    effective_n: np.ndarray  # (ny, nx)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        ny, nx = self.mean.shape
        return self.origin[0] + self.cell_m * np.arange(nx), self.origin[1] + self.cell_m * np.arange(ny)


def signal_grid(
    xy: np.ndarray,
    values: np.ndarray,
    cell_m: float = 2.0,
    bandwidth_m: float = 3.0,
    support_m: float = 6.0,
    bounds: tuple[float, float, float, float] | None = None,
) -> SignalGrid:
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    values = np.asarray(values, dtype=float)
    if values.shape != (xy.shape[0],) or xy.shape[0] == 0:
        raise ValueError("one value per position, at least one")
    if not (cell_m > 0 and bandwidth_m > 0 and support_m > 0):
        raise ValueError("cell_m, bandwidth_m and support_m must be positive")
    x0, y0, x1, y1 = bounds or (xy[:, 0].min(), xy[:, 1].min(), xy[:, 0].max(), xy[:, 1].max())
    gx = np.arange(x0, x1 + cell_m / 2, cell_m)
    gy = np.arange(y0, y1 + cell_m / 2, cell_m)
    cells = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    d2 = np.sum((cells[:, None, :] - xy[None, :, :]) ** 2, axis=-1)
    w = np.exp(-0.5 * d2 / bandwidth_m**2)
    total = w.sum(axis=1)
    inside = (d2.min(axis=1) <= support_m**2) & (total > 0)
    safe = np.maximum(total, 1e-300)
    mean = (w @ values) / safe
    spread = (w @ values**2) / safe - mean**2
    effective = total**2 / np.maximum(np.sum(w * w, axis=1), 1e-300)
    shape = (gy.size, gx.size)

    def masked(a: np.ndarray) -> np.ndarray:
        return np.where(inside, a, np.nan).reshape(shape)

    return SignalGrid(
        np.array([gx[0], gy[0]]),
        float(cell_m),
        masked(mean),
        masked(np.sqrt(np.maximum(spread, 0.0))),
        masked(effective),
    )


@dataclass(frozen=True)
class FingerprintGrid:
    xy: np.ndarray  # (C, 2) centres of the cells that hold scans
    rss: np.ndarray  # (C, A) mean RSS, NaN where never heard
    visibility: np.ndarray  # (C, A) how many of the cell's scans heard each AP
    scans: np.ndarray  # (C,) scans per cell


def fingerprint_grid(xy: np.ndarray, rss: np.ndarray, cell_m: float = 5.0) -> FingerprintGrid:
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    rss = np.asarray(rss, dtype=float)
    if rss.ndim != 2 or rss.shape[0] != xy.shape[0]:
        raise ValueError("one RSS row (NaN = not heard) per position")
    if cell_m <= 0:
        raise ValueError("cell_m must be positive")
    keys = np.floor(xy / cell_m).astype(np.int64)
    cells, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    heard = np.isfinite(rss)
    visibility = np.zeros((cells.shape[0], rss.shape[1]))
    sums = np.zeros_like(visibility)
    np.add.at(visibility, inverse, heard.astype(float))
    np.add.at(sums, inverse, np.where(heard, rss, 0.0))
    mean = np.where(visibility > 0, sums / np.maximum(visibility, 1.0), np.nan)
    scans = np.bincount(inverse, minlength=cells.shape[0]).astype(float)
    return FingerprintGrid((cells + 0.5) * cell_m, mean, visibility, scans)


def localise_knn(db: FingerprintGrid, query_rss: np.ndarray, k: int = 7) -> np.ndarray:
    """(Q, 2) positions of the query scans (rows of RSS, NaN = not heard); NaN rows when nothing matches."""
    both = np.vstack([db.rss, np.asarray(query_rss, dtype=float)])
    distance = fingerprint_matrix(both)[db.rss.shape[0] :, : db.rss.shape[0]]
    k = min(k, db.rss.shape[0])
    nearest = np.argsort(distance, axis=1, kind="stable")[:, :k]
    d = np.take_along_axis(distance, nearest, axis=1)
    w = np.where(np.isfinite(d), 1.0 / np.maximum(d, 1e-3), 0.0)
    total = w.sum(axis=1, keepdims=True)
    estimate: np.ndarray = np.einsum("qk,qkc->qc", w, db.xy[nearest]) / np.where(total > 0, total, np.nan)
    return estimate


def localise_kernel(
    db: FingerprintGrid, query_counts: np.ndarray, n: int = 10, alpha: float = 1.0
) -> np.ndarray:
    """(Q, 2) positions of query windows (AP sighting counts) by KL-kernel regression over the cells'
    visibility: the kernel-weighted mean of the ``n`` most similar cells."""
    cells = visibility_multinomials(db.visibility)
    queries = visibility_multinomials(np.asarray(query_counts, dtype=float))
    kernel = kl_kernel(queries, cells, alpha=alpha)
    n = min(n, cells.shape[0])
    nearest = np.argsort(-kernel, axis=1, kind="stable")[:, :n]
    w = np.take_along_axis(kernel, nearest, axis=1)
    total = w.sum(axis=1, keepdims=True)
    estimate: np.ndarray = np.einsum("qk,qkc->qc", w, db.xy[nearest]) / np.where(total > 0, total, np.nan)
    return estimate
