"""Zone outlines and the share of a cloud inside them, against matplotlib's point-in-polygon as the oracle."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.path import Path

from slam_core.zones.geometry import MAX_VERTICES, inside_shares, ring_problem, zone_set

SQUARE = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])


def _star(rng: np.random.Generator, n: int, centre: tuple[float, float]) -> np.ndarray:
    """A simple (star-shaped) polygon of ``n`` vertices: random radii at sorted random angles."""
    angles = (np.arange(n) + rng.uniform(0.0, 0.9, n)) * 2 * np.pi / n  # no gap of half a turn
    radii = rng.uniform(2.0, 10.0, n)
    return np.column_stack([centre[0] + radii * np.cos(angles), centre[1] + radii * np.sin(angles)])


@pytest.mark.parametrize(
    ("ring", "problem"),
    [
        (SQUARE, None),
        (np.vstack([SQUARE, SQUARE[:1]]), None),  # closed, as GeoJSON writes it
        (np.array([[0.0, 0.0], [4.0, 4.0], [4.0, 0.0], [0.0, 4.0]]), "crosses itself: its edges 0 and 2"),
        (np.array([[0.0, 0.0], [4.0, 0.0], [2.0, 0.0], [2.0, 3.0]]), "crosses itself: its edges 0 and 1"),
        (np.array([[0.0, 0.0], [4.0, 0.0], [8.0, 0.0]]), "encloses no area"),
        (np.array([[0.0, 0.0], [4.0, 0.0]]), "at least three"),
        (np.array([[0.0, 0.0], [np.nan, 0.0], [4.0, 4.0]]), "finite"),
        (np.zeros((3, 3)), "list of [x, y]"),
        (np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [2.0, 0.0], [0.0, 4.0]]), "crosses itself"),
    ],
)
def test_an_outline_is_a_simple_ring_with_an_area(ring: np.ndarray, problem: str | None) -> None:
    found = ring_problem(ring)
    if problem is None:
        assert found is None
    else:
        assert found is not None
        assert problem in found


def test_an_outline_has_a_bounded_number_of_vertices() -> None:
    ring = _star(np.random.default_rng(0), MAX_VERTICES + 1, (0.0, 0.0))
    assert f"at most {MAX_VERTICES}" in (ring_problem(ring) or "")
    with pytest.raises(ValueError, match="zone 1: the outline crosses itself"):
        zone_set([SQUARE, np.array([[0.0, 0.0], [4.0, 4.0], [4.0, 0.0], [0.0, 4.0]])], [0, 0])


def test_random_simple_stars_are_simple() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        assert ring_problem(_star(rng, int(rng.integers(3, 40)), (0.0, 0.0))) is None


def test_the_share_inside_is_the_weighted_share_of_particles_the_oracle_puts_inside() -> None:
    rng = np.random.default_rng(2)
    rings = [_star(rng, int(rng.integers(3, 30)), (rng.uniform(-5, 5), rng.uniform(-5, 5))) for _ in range(6)]
    zones = zone_set(rings, [0, 0, 0, 1, 1, 0])
    n_users, m = 9, 75
    px = rng.uniform(-15.0, 15.0, (n_users, m))
    py = rng.uniform(-15.0, 15.0, (n_users, m))
    logw = rng.normal(0.0, 1.0, (n_users, m))
    users = np.array([0, 2, 3, 5, 8])
    user_level = np.array([0, 1, 0, 0, 1])
    got = inside_shares(
        px, py, logw, users, user_level, zones.level, zones.start, zones.vx, zones.vy, zones.bbox
    )
    assert got.shape == (users.size, len(zones))
    for k, u in enumerate(users):
        w = np.exp(logw[u] - logw[u].max())
        w /= w.sum()
        for z, ring in enumerate(rings):
            expected = 0.0
            if zones.level[z] == user_level[k]:
                expected = float(w @ Path(ring).contains_points(np.column_stack([px[u], py[u]])))
            assert got[k, z] == pytest.approx(expected, abs=1e-12), (k, z)
    assert np.all((got >= 0.0) & (got <= 1.0 + 1e-12))


def test_a_cloud_far_from_a_zone_or_on_another_floor_is_not_in_it() -> None:
    zones = zone_set([SQUARE, SQUARE], [0, 1])
    px = np.full((1, 10), 2.0)
    py = np.full((1, 10), 2.0)
    logw = np.zeros((1, 10))
    got = inside_shares(
        px, py, logw, np.array([0]), np.array([0]), zones.level, zones.start, zones.vx, zones.vy, zones.bbox
    )
    np.testing.assert_allclose(got, [[1.0, 0.0]])
    far = inside_shares(
        px + 50,
        py,
        logw,
        np.array([0]),
        np.array([0]),
        zones.level,
        zones.start,
        zones.vx,
        zones.vy,
        zones.bbox,
    )
    np.testing.assert_allclose(far, [[0.0, 0.0]])
    assert len(zone_set([], [])) == 0
