"""The numba Madgwick filter against ``ahrs`` (the oracle), and the rotation-vector helpers."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from ahrs.filters import Madgwick

from slam_core.sensing.pdr.orientation import azimuth, madgwick_run, quaternion_from_rotation_vector


def _imu(n: int = 400, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = 1.7e12 + np.cumsum(rng.uniform(15.0, 25.0, n))  # uneven sampling, as phones deliver
    gyr = rng.normal(0, 0.4, (n, 3))
    acc = np.array([0.3, 0.2, 9.8]) + rng.normal(0, 0.6, (n, 3))
    mag = np.array([20.0, 5.0, -40.0]) + rng.normal(0, 1.0, (n, 3))
    return t, gyr, acc, mag


@pytest.mark.parametrize("use_mag", [False, True])
def test_matches_ahrs(use_mag: bool) -> None:
    t, gyr, acc, mag = _imu()
    oracle = Madgwick(gain=0.041)
    q_ref = np.array([1.0, 0.0, 0.0, 0.0])
    expected = [q_ref]
    for i in range(1, len(t)):
        dt = (t[i] - t[i - 1]) * 1e-3
        q_ref = (
            oracle.updateMARG(q_ref, gyr[i], acc[i], mag[i], dt=dt)
            if use_mag
            else oracle.updateIMU(q_ref, gyr[i], acc[i], dt=dt)
        )
        expected.append(q_ref)
    ours = madgwick_run(
        np.array([1.0, 0, 0, 0]), t, gyr, acc, mag if use_mag else np.zeros_like(mag), 0.041, math.nan
    )
    np.testing.assert_allclose(ours, np.array(expected), atol=1e-12)


def test_a_walk_in_one_second_batches_equals_the_whole_walk() -> None:
    t, gyr, acc, mag = _imu(900, seed=1)
    whole = madgwick_run(np.array([1.0, 0, 0, 0]), t, gyr, acc, mag, 0.041, math.nan)
    q = np.array([1.0, 0, 0, 0])
    last = math.nan
    parts = []
    edges = np.searchsorted(t, np.arange(t[0], t[-1] + 1000, 1000))
    for a, b in itertools.pairwise(edges):
        parts.append(madgwick_run(q, t[a:b], gyr[a:b], acc[a:b], mag[a:b], 0.041, last))
        last = t[b - 1] if b > a else last
    np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_quaternions_stay_unit_and_finite() -> None:
    t, gyr, acc, mag = _imu(300, seed=2)
    acc[50] = 0.0  # free fall: no gravity reference for one sample
    gyr[60] = 0.0  # perfectly still gyroscope
    q = madgwick_run(np.array([1.0, 0, 0, 0]), t, gyr, acc, mag, 0.041, math.nan)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, 90.0, -135.0])
def test_azimuth_of_a_flat_phone(yaw_deg: float) -> None:
    """A flat phone rotated counter-clockwise by yaw about up points its y axis yaw west of north."""
    half = math.radians(yaw_deg) / 2
    xyz = np.array([0.0, 0.0, math.sin(half)])
    q = quaternion_from_rotation_vector(xyz)  # w reconstructed
    assert q[0] == pytest.approx(math.cos(half))
    assert float(azimuth(q)) == pytest.approx(-math.radians(yaw_deg), abs=1e-12)
