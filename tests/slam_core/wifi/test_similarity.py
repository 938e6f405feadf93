"""The WiFi similarity kernels against their references: Eq. 3 and the union-fingerprint distance, per pair
and for every pair, on random scans with ties, repeated and missing APs, and empty scans."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.encounters.models import WifiEq3Params, wifi_eq3_similarity
from slam_core.wifi import similarity
from slam_core.wifi.pairs import dense_eq3_matrix, fingerprint_matrix
from tests.slam_core.wifi.reference import (
    eq3_dense,
    eq3_matrix_products,
    eq3_sparse,
    union_rms_dense,
    union_rms_sparse,
)


def _scans(n: int = 30, aps: int = 25, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rss = rng.uniform(-105.0, -40.0, (n, aps)).round()  # integer dBm: ties happen, as on phones
    rss[rng.random((n, aps)) < 0.6] = np.nan
    rss[3] = np.nan  # an empty scan
    return rss


def _top(rng: np.random.Generator, aps: int, n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    k = int(rng.integers(0, n + 1))
    ap = np.full(n, -1, dtype=np.int64)
    ap[:k] = rng.choice(aps, size=k, replace=False)
    rss = np.zeros(n)
    rss[:k] = rng.uniform(-90.0, -40.0, k).round()
    return ap, rss


def test_eq3_kernel_matches_the_sparse_definition() -> None:
    rng = np.random.default_rng(0)
    for _ in range(2_000):
        ap_a, rss_a = _top(rng, 12)
        ap_b, rss_b = _top(rng, 12)
        table_a = {int(a): float(r) for a, r in zip(ap_a, rss_a, strict=True) if a >= 0}
        table_b = {int(a): float(r) for a, r in zip(ap_b, rss_b, strict=True) if a >= 0}
        sim, n = similarity.eq3(ap_a, rss_a, ap_b, rss_b)
        expected, n_expected = eq3_sparse(table_a, table_b)
        assert n == n_expected
        assert sim == pytest.approx(expected, rel=1e-12) if n else math.isinf(sim)


def test_eq3_of_a_pair_is_symmetric_and_zero_on_itself() -> None:
    ap = np.array([4, 1, 7, -1, -1])
    rss = np.array([-50.0, -60.0, -70.0, 0.0, 0.0])
    assert similarity.eq3(ap, rss, ap, rss) == (0.0, 3)
    other = np.array([7, 4, 9, 2, -1])
    other_rss = np.array([-72.0, -55.0, -40.0, -80.0, 0.0])
    assert similarity.eq3(ap, rss, other, other_rss) == similarity.eq3(other, other_rss, ap, rss)
    assert similarity.eq3(ap, rss, other, other_rss)[0] == pytest.approx(math.hypot(5.0, 2.0) / 2)


def test_union_rms_kernel_matches_the_sparse_definition() -> None:
    rng = np.random.default_rng(1)
    floor = -100.0
    for _ in range(2_000):
        a = {int(k): float(rng.uniform(-110, -40)) for k in rng.choice(20, rng.integers(0, 8), replace=False)}
        b = {int(k): float(rng.uniform(-110, -40)) for k in rng.choice(20, rng.integers(0, 8), replace=False)}
        ga = {k: max(v, floor) - floor for k, v in a.items()}
        gb = {k: max(v, floor) - floor for k, v in b.items()}
        shared = a.keys() & b.keys()
        d = similarity.union_rms(
            sum(g * g for g in ga.values()),
            sum(g * g for g in gb.values()),
            sum(ga[k] * gb[k] for k in shared),
            len(a),
            len(b),
            len(shared),
        )
        expected = union_rms_sparse(a, b, floor)
        assert d == pytest.approx(expected, abs=1e-6) if math.isfinite(expected) else math.isinf(d)


@pytest.mark.parametrize("min_common", [1, 2])
def test_every_caller_of_eq3_agrees_with_the_references(min_common: int) -> None:
    rss = _scans()
    params = WifiEq3Params(min_common=min_common)
    matrix = dense_eq3_matrix(rss, params.strongest_n, min_common)
    products = eq3_matrix_products(rss, params.strongest_n, min_common)
    assert np.array_equal(np.isinf(matrix), np.isinf(products))
    finite = np.isfinite(products)
    np.testing.assert_allclose(matrix[finite], products[finite], atol=1e-9)
    for i in range(0, rss.shape[0], 3):
        for j in range(rss.shape[0]):
            sim, n = wifi_eq3_similarity(rss[i], rss[j], params)
            expected, n_expected = eq3_dense(rss[i], rss[j], params.strongest_n, min_common)
            assert n == n_expected
            assert sim == pytest.approx(expected, abs=1e-9) if math.isfinite(expected) else math.isinf(sim)


def test_the_union_matrix_agrees_with_the_reference() -> None:
    rss = _scans(seed=2)
    ours = fingerprint_matrix(rss, floor_dbm=-100.0)
    for i in range(rss.shape[0]):
        for j in range(rss.shape[0]):
            expected = union_rms_dense(rss[i], rss[j], -100.0)
            assert (
                ours[i, j] == pytest.approx(expected, abs=1e-6)
                if math.isfinite(expected)
                else (math.isinf(ours[i, j]))
            )
    assert np.allclose(np.diag(ours)[np.isfinite(np.diag(ours))], 0.0, atol=1e-6)
