"""SignalSLAM pieces: kernels against direct computations, Eq. 4 on a walk with known errors, every edge's
Jacobian against a numerical one, and small synthetic floors where the optimum is known."""

from __future__ import annotations

import math
from typing import Any

import gtsam
import numpy as np
import pytest

from slam_core.signalslam.calibration import CalibrationGrid, CalibrationPrior, calibrate_segment, dead_reckon
from slam_core.signalslam.graph import SignalGraphParams, Walk, position_at, solve
from slam_core.signalslam.similarity import gaussian_kernel, kl_kernel, symmetric_kl, visibility_multinomials


def test_kl_kernel_matches_a_direct_computation() -> None:
    rng = np.random.default_rng(0)
    counts = rng.poisson(1.0, (6, 9)).astype(float)
    counts[2] = 0.0  # a window that heard nothing
    p = visibility_multinomials(counts, epsilon=1e-3)
    assert np.allclose(p.sum(axis=1), 1.0)
    kernel = kl_kernel(p, alpha=0.7)
    for i in range(6):
        for j in range(6):
            direct = np.sum(p[i] * np.log(p[i] / p[j])) + np.sum(p[j] * np.log(p[j] / p[i]))
            assert symmetric_kl(p)[i, j] == pytest.approx(direct, abs=1e-9)
            assert kernel[i, j] == pytest.approx(math.exp(-0.7 * direct), rel=1e-9)
    assert np.allclose(np.diag(kernel), 1.0)
    assert np.allclose(kernel, kernel.T)
    with pytest.raises(ValueError, match="non-negative"):
        visibility_multinomials(-np.ones((2, 2)))


def test_gaussian_kernel_matches_a_direct_computation() -> None:
    a = np.array([40.0, 45.0, 52.0])  # magnetic magnitude per window (uT)
    b = np.array([41.0, 60.0])
    kernel = gaussian_kernel(a, b, alpha=0.1)
    for i in range(3):
        for j in range(2):
            assert kernel[i, j] == pytest.approx(math.exp(-0.1 * (a[i] - b[j]) ** 2))


def test_eq4_recovers_stride_scale_and_offset() -> None:
    rng = np.random.default_rng(1)
    headings = np.cumsum(rng.normal(0, 0.05, 60)) + 0.3
    lengths = rng.uniform(0.6, 0.8, 60)
    start = np.array([3.0, 4.0])
    truth_end = dead_reckon(lengths, headings, start, scale=1.12, offset=math.radians(-9.0))[-1]
    scale, offset, residual = calibrate_segment(lengths, headings, start, truth_end, CalibrationGrid())
    assert scale == pytest.approx(1.12, abs=0.011)
    assert math.degrees(offset) == pytest.approx(-9.0, abs=1.01)
    assert residual < 0.5
    with pytest.raises(ValueError, match="non-empty"):
        calibrate_segment(np.zeros(0), np.zeros(0), start, start, CalibrationGrid())


def _loop_walk(n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """A square walked once around: 4 x 15 steps of 0.7 m, ending where it started."""
    headings = np.repeat(np.radians([0.0, 90.0, 180.0, 270.0]), n // 4)
    return np.full(n, 0.7), headings


def test_the_prior_keeps_a_loop_walk_near_its_dead_reckoning_where_eq4_is_blind() -> None:
    lengths, headings = _loop_walk()
    start = np.array([5.0, 5.0])
    end = start + np.array([0.4, -0.3])
    # both landmarks at one place: every rotation and scale of a closed loop lands on it
    _, offset, _ = calibrate_segment(lengths, headings, start, end, CalibrationGrid())
    assert abs(math.degrees(offset)) > 20.0  # Eq. 4 alone turns the loop by whatever fits the 0.5 m
    scale, offset, _ = calibrate_segment(lengths, headings, start, end, CalibrationGrid(), CalibrationPrior())
    assert abs(math.degrees(offset)) <= 2.0
    assert abs(scale - 1.0) <= 0.03


def test_the_prior_leaves_a_long_straight_walk_to_its_landmarks() -> None:
    rng = np.random.default_rng(1)
    headings = np.cumsum(rng.normal(0, 0.02, 120)) + 0.3
    lengths = rng.uniform(0.6, 0.8, 120)
    start = np.array([3.0, 4.0])
    end = dead_reckon(lengths, headings, start, scale=1.12, offset=math.radians(-9.0))[-1]
    plain = calibrate_segment(lengths, headings, start, end, CalibrationGrid())
    posterior = calibrate_segment(lengths, headings, start, end, CalibrationGrid(), CalibrationPrior())
    assert posterior[0] == pytest.approx(plain[0], abs=0.021)
    assert math.degrees(posterior[1]) == pytest.approx(math.degrees(plain[1]), abs=1.01)
    with pytest.raises(ValueError, match="positive"):
        CalibrationPrior(scale_sigma=0.0)


@pytest.mark.parametrize("solver", ["lm", "isam2"])
def test_the_start_heading_prior_holds_a_closed_loop_to_the_phones_heading(solver: str) -> None:
    lengths, headings = _loop_walk()
    t = 1000 * np.arange(lengths.size + 1)
    truth = dead_reckon(lengths, headings, np.zeros(2))
    # the dead reckoning is right; the landmark at the end is 1.2 m off, as a tag read a step late
    walk = Walk(t_ms=t.astype(np.int64), lengths=lengths, headings=headings, start=np.zeros(2),
                end=np.array([1.2, 0.0]), window_t=t[1:].astype(np.int64),
                window_counts=np.zeros((lengths.size, 0)))  # fmt: skip
    held = solve([walk], SignalGraphParams(iterations=0, solver=solver, chunk_poses=7))
    error = np.linalg.norm(held.graphslam[0][1:] - truth, axis=1)
    assert error.max() < 1.3  # the chain bends its last steps onto the late landmark, no more
    assert np.linalg.norm(held.graphslam[0][1:31] - truth[:30], axis=1).max() < 0.6


def _numerical_jacobian(factor: Any, values: gtsam.Values, key: int) -> np.ndarray:
    base = values.atPose2(key)
    columns = []
    for k in range(3):
        delta = np.zeros(3)
        delta[k] = 1e-6
        plus, minus = gtsam.Values(values), gtsam.Values(values)
        plus.update(key, base.retract(delta))
        minus.update(key, base.retract(-delta))
        columns.append((factor.unwhitenedError(plus) - factor.unwhitenedError(minus)) / 2e-6)
    return np.column_stack(columns)


@pytest.mark.parametrize("edge", ["motion", "landmark", "signal"])
def test_edge_jacobians_match_numerical_ones(edge: str) -> None:
    k0, k1 = gtsam.symbol("x", 0), gtsam.symbol("x", 1)
    values = gtsam.Values()
    values.insert(k0, gtsam.Pose2(1.0, 2.0, 0.4))
    values.insert(k1, gtsam.Pose2(1.5, 2.9, 0.9))
    sigmas = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.05, 0.02]))
    factor: Any
    if edge == "motion":
        factor = gtsam.BetweenFactorPose2(k0, k1, gtsam.Pose2(0.7, 0.1, 0.3), sigmas)
        keys = [k0, k1]
    else:
        noise = gtsam.noiseModel.Isotropic.Sigma(2, 0.5 if edge == "landmark" else 5.0)
        factor = gtsam.PoseTranslationPrior2D(k1, np.array([2.0, 3.0]), noise)
        keys = [k1]
    linear = factor.linearize(values)
    jacobian, _ = linear.jacobian()
    whitening = np.linalg.cholesky(np.linalg.inv(factor.noiseModel().covariance())).T
    for i, key in enumerate(keys):
        analytic = jacobian[:, 3 * i : 3 * i + 3]
        numerical = whitening @ _numerical_jacobian(factor, values, key)
        np.testing.assert_allclose(analytic, numerical, atol=1e-6)


def _corridor_walk(bulge: float, n: int = 40, t0: int = 0, aps: int = 20) -> tuple[Walk, np.ndarray]:
    """Walk east along y = 0 for n steps of 1 m; the dead reckoning's heading wanders by ``bulge`` rad in
    the middle (zero at both ends, so landmarks at the ends cannot see it). AP visibility depends on x."""
    k = np.arange(1, n + 1)
    truth = np.column_stack([k.astype(float), np.zeros(n)])
    headings = bulge * np.sin(2 * np.pi * k / n)  # deviates and comes back: both ends stay right
    t = t0 + 1000 * np.arange(n + 1)
    window_t = t[1:]
    ap_x = np.linspace(0, n, aps)
    counts = np.round(6 * np.exp(-((truth[:, 0:1] - ap_x[None, :]) ** 2) / 8.0))
    cell_x = np.array([0.0, n / 2, float(n)])  # three LTE cells: RSRP falls 1.5 dB per metre from each
    rsrp = -60.0 - 1.5 * np.abs(truth[:, 0:1] - cell_x[None, :])
    walk = Walk(
        t_ms=t.astype(np.int64),
        lengths=np.ones(n),
        headings=headings,
        start=np.zeros(2),
        end=truth[-1],
        window_t=window_t.astype(np.int64),
        window_counts=counts,
        window_lte=np.where(rsrp > -120.0, rsrp, np.nan),
    )
    return walk, truth


@pytest.mark.parametrize("solver", ["lm", "isam2"])
def test_graphslam_closes_a_walk_between_its_landmarks(solver: str) -> None:
    walk, truth = _corridor_walk(bulge=0.0)
    rotated = Walk(**{**walk.__dict__, "headings": walk.headings + math.radians(8.0)})
    result = solve([rotated], SignalGraphParams(iterations=0, solver=solver, chunk_poses=7))
    assert np.linalg.norm(result.raw[0][1:] - truth, axis=1).max() > 5.0
    # a constant heading bias costs the chain little: its start heading has only a 10 deg prior, against the
    # landmark 40 m away (with the prior off it costs nothing)
    assert np.linalg.norm(result.graphslam[0][1:] - truth, axis=1).max() < 0.2
    free = solve(
        [rotated], SignalGraphParams(iterations=0, solver=solver, chunk_poses=7, start_heading_prior=False)
    )
    assert np.linalg.norm(free.graphslam[0][1:] - truth, axis=1).max() < 0.1
    scaled = Walk(**{**rotated.__dict__, "lengths": walk.lengths * 1.1})
    result = solve([scaled], SignalGraphParams(iterations=0, solver=solver, chunk_poses=7))
    raw_error = np.linalg.norm(result.raw[0][1:] - truth, axis=1).mean()
    # a scale error is spread over the steps' length noise (no scale variable in the pose graph) ...
    assert np.linalg.norm(result.graphslam[0][1:] - truth, axis=1).mean() < 0.2 * raw_error
    # ... while Eq. 4 models it exactly
    assert np.linalg.norm(result.calibrated[0][1:] - truth, axis=1).max() < 0.3


@pytest.mark.parametrize(("solver", "modality"), [("lm", "wifi"), ("isam2", "wifi"), ("lm", "lte")])
def test_signal_edges_pull_a_walk_onto_similar_places_of_another(solver: str, modality: str) -> None:
    """Three walks agree on a straight corridor; a fourth's dead reckoning bulges in the middle. Signal edges
    (WiFi visibility, or LTE RSRP alone) say the fourth passed the same places: the majority pulls it onto
    the corridor."""
    walks = [_corridor_walk(bulge=0.0, t0=100_000 * i)[0] for i in range(3)]
    wandering, truth = _corridor_walk(bulge=0.25, t0=400_000)
    params = SignalGraphParams(signal_sigma_m=1.0, solver=solver, chunk_poses=11, modalities=(modality,))
    result = solve([*walks, wandering], params)
    middle = slice(10, 30)

    def error(xy: np.ndarray) -> float:
        return float(np.linalg.norm(xy[1:][middle] - truth[middle], axis=1).mean())

    graph_error = error(result.graphslam[3])
    assert graph_error > 2.0
    assert error(result.signalslam[3]) < 0.6 * graph_error
    for i in range(3):  # the majority moves much less than the outlier is corrected
        assert error(result.signalslam[i]) < 0.5 * graph_error
    for xy in result.signalslam:
        assert np.all(np.isfinite(xy))


def test_position_at_interpolates_between_poses() -> None:
    xy = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 4.0]])
    t = np.array([0, 1000, 2000])
    np.testing.assert_allclose(position_at(t, xy, np.array([500.0, 1500.0])), [[1.0, 0.0], [2.0, 2.0]])


def test_modalities_multiply_and_a_missing_one_is_neutral() -> None:
    from slam_core.signalslam.graph import signal_neighbours

    rng = np.random.default_rng(4)
    wifi = rng.poisson(2.0, (6, 5)).astype(float)
    beacons = rng.poisson(1.0, (6, 3)).astype(float)
    beacons[0] = 0.0  # window 0 heard no beacon
    magnetic = np.array([40.0, np.nan, 45.0, 41.0, 60.0, 42.0])
    t, one, zero = np.array([0, 1000]), np.ones(1), np.zeros(1)
    windows = np.array([0, 1, 2]) * 1000
    walks = [
        Walk(t, one, zero, np.zeros(2), np.ones(2), windows, wifi[:3], beacons[:3], magnetic[:3]),
        Walk(t, one, zero, np.zeros(2), np.ones(2), windows, wifi[3:], beacons[3:], magnetic[3:]),
    ]
    only_wifi = signal_neighbours(walks, SignalGraphParams(neighbours=3))
    both = signal_neighbours(
        walks, SignalGraphParams(neighbours=3, modalities=("wifi", "bluetooth", "magnetic"))
    )
    # window 0 has no beacons: its weights change only through the magnetic kernel
    for col in range(3):
        j = int(both[1][0, col])
        assert j >= 3  # neighbours come from the other walk
    kernel_wifi = dict(zip(only_wifi[1][0], only_wifi[2][0], strict=True))
    for j, w in zip(both[1][0], both[2][0], strict=True):
        expected = kernel_wifi[j] * math.exp(
            -SignalGraphParams().magnetic_alpha * (magnetic[0] - magnetic[j]) ** 2
        )
        assert w == pytest.approx(expected, rel=1e-9)
    with pytest.raises(ValueError, match="unknown modalities"):
        SignalGraphParams(modalities=("lte-in-a-mall",))
    with pytest.raises(ValueError, match="solver"):
        SignalGraphParams(solver="gauss-newton-by-hand")


def test_union_gaussian_kernel_matches_a_direct_computation() -> None:
    from slam_core.signalslam.similarity import union_gaussian_kernel

    nan = math.nan
    rows = np.array([[-80.0, -95.0, nan], [-82.0, nan, -100.0], [nan, nan, nan], [-130.0, nan, nan]])
    alpha, floor = 0.02, -120.0
    kernel = union_gaussian_kernel(rows, alpha, floor)
    for i in range(4):
        for j in range(4):
            union = [c for c in range(3) if math.isfinite(rows[i, c]) or math.isfinite(rows[j, c])]
            if not union:
                assert kernel[i, j] == 1.0
                continue

            def level(v: float) -> float:
                return max(v, floor) if math.isfinite(v) else floor

            d = sum((level(rows[i, c]) - level(rows[j, c])) ** 2 for c in union) / len(union)
            assert kernel[i, j] == pytest.approx(math.exp(-alpha * d), rel=1e-12)
    with pytest.raises(ValueError, match="windows, cells"):
        union_gaussian_kernel(np.zeros(3), alpha, floor)


def test_window_means_average_each_column_within_the_window() -> None:
    from slam_core.signalslam.windows import window_means

    centres = np.array([0, 10_000, 30_000])
    means = window_means(
        centres, np.array([1_000, 4_000, 9_000]), [{0: -90.0}, {0: -100.0, 2: -80.0}, {1: -70.0}], 3
    )
    np.testing.assert_allclose(means[0], [-95.0, np.nan, -80.0])
    np.testing.assert_allclose(means[1], [np.nan, -70.0, np.nan])  # 4 s is 6 s from this centre
    assert np.all(np.isnan(means[2]))


def test_lte_kernel_joins_the_product_and_a_window_without_lte_is_neutral() -> None:
    from slam_core.signalslam.graph import signal_neighbours
    from slam_core.signalslam.similarity import union_gaussian_kernel

    rng = np.random.default_rng(5)
    wifi = rng.poisson(2.0, (6, 5)).astype(float)
    lte = rng.uniform(-110.0, -80.0, (6, 2))
    lte[0] = np.nan  # window 0 heard no cell
    t, one, zero = np.array([0, 1000]), np.ones(1), np.zeros(1)
    windows = np.array([0, 1, 2]) * 1000
    walks = [
        Walk(t, one, zero, np.zeros(2), np.ones(2), windows, wifi[:3], window_lte=lte[:3]),
        Walk(t, one, zero, np.zeros(2), np.ones(2), windows, wifi[3:], window_lte=lte[3:]),
    ]
    only_wifi = signal_neighbours(walks, SignalGraphParams(neighbours=3))
    both = signal_neighbours(walks, SignalGraphParams(neighbours=3, modalities=("wifi", "lte")))
    np.testing.assert_allclose(both[2][0], only_wifi[2][0])  # window 0: LTE says nothing
    p = SignalGraphParams()
    lte_kernel = union_gaussian_kernel(lte, p.lte_alpha, p.lte_floor_dbm)
    kernel_wifi = dict(zip(only_wifi[1][1], only_wifi[2][1], strict=True))
    for j, w in zip(both[1][1], both[2][1], strict=True):
        if j in kernel_wifi:
            assert w == pytest.approx(kernel_wifi[j] * lte_kernel[1, j], rel=1e-9)
