"""Signal maps, the fingerprint grid and WiFi localisation against direct computations and known layouts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.signalslam.maps import fingerprint_grid, localise_kernel, localise_knn, signal_grid


def test_signal_grid_is_the_kernel_regression_with_its_spread() -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 20, (60, 2))
    values = -40.0 - 2.0 * xy[:, 0] + rng.normal(0, 1.0, 60)
    grid = signal_grid(xy, values, cell_m=2.0, bandwidth_m=3.0, support_m=6.0)
    gx, gy = grid.centres()
    for iy, ix in ((3, 4), (5, 1), (8, 8)):
        cell = np.array([gx[ix], gy[iy]])
        d2 = np.sum((xy - cell) ** 2, axis=1)
        w = np.exp(-0.5 * d2 / 9.0)
        mean = w @ values / w.sum()
        if d2.min() <= 36.0:
            assert grid.mean[iy, ix] == pytest.approx(mean)
            assert grid.std[iy, ix] == pytest.approx(math.sqrt(w @ (values - mean) ** 2 / w.sum()), rel=1e-6)
            assert grid.effective_n[iy, ix] == pytest.approx(w.sum() ** 2 / np.sum(w * w))
    far = signal_grid(np.array([[0.0, 0.0], [30.0, 0.0]]), np.array([-50.0, -60.0]), 2.0, 3.0, 6.0)
    assert np.isnan(far.mean[0, far.mean.shape[1] // 2])  # nothing within 6 m of the middle
    with pytest.raises(ValueError, match="one value per position"):
        signal_grid(np.zeros((2, 2)), np.zeros(3))


def test_fingerprint_grid_bins_and_averages() -> None:
    xy = np.array([[1.0, 1.0], [2.0, 4.0], [7.0, 1.0]])
    rss = np.array([[-50.0, np.nan], [-60.0, -70.0], [np.nan, -80.0]])
    grid = fingerprint_grid(xy, rss, cell_m=5.0)
    order = np.argsort(grid.xy[:, 0])
    np.testing.assert_allclose(grid.xy[order], [[2.5, 2.5], [7.5, 2.5]])
    np.testing.assert_allclose(grid.rss[order][0], [-55.0, -70.0])
    assert np.isnan(grid.rss[order][1, 0])
    assert grid.rss[order][1, 1] == -80.0
    np.testing.assert_allclose(grid.visibility[order], [[2.0, 1.0], [0.0, 1.0]])
    np.testing.assert_allclose(grid.scans[order], [2.0, 1.0])


def test_localisation_finds_the_matching_place() -> None:
    # a corridor of 10 cells, each with its own loud AP and a gradient of the others
    xs = np.arange(10) * 5.0 + 2.5
    aps = np.arange(10) * 5.0 + 2.5
    rss = -40.0 - 1.5 * np.abs(xs[:, None] - aps[None, :])
    rss[rss <= -62.0] = np.nan  # APs further than ~15 m are not heard
    db = fingerprint_grid(np.column_stack([xs, np.zeros(10)]), rss, 5.0)
    query = rss[[2, 7]] + np.random.default_rng(1).normal(0, 1.0, (2, 10))
    knn = localise_knn(db, query, k=1)
    np.testing.assert_allclose(knn, [[12.5, 2.5], [37.5, 2.5]])
    visible = np.isfinite(rss).astype(float)
    kernel = localise_kernel(db, visible[[2, 7]], n=3, alpha=5.0)
    assert abs(kernel[0, 0] - 12.5) < 3.0
    assert abs(kernel[1, 0] - 37.5) < 3.0
