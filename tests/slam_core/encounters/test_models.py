"""Encounter models: Eq. 3 against a direct computation, range-model fits and their inversion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_core.encounters.models import (
    RangeModel,
    WifiEq3Params,
    encounter_model,
    fit_range_model,
    strongest,
    wifi_eq3_similarity,
)

NAN = np.nan


def test_eq3_matches_a_direct_computation() -> None:
    a = np.array([-40.0, -50.0, -60.0, -70.0, -80.0, -90.0, NAN])
    b = np.array([-42.0, NAN, -65.0, -70.0, -60.0, -91.0, -45.0])
    sim, n = wifi_eq3_similarity(a, b, WifiEq3Params(strongest_n=5))
    top_a = {0, 1, 2, 3, 4}  # the five strongest of a
    top_b = {0, 6, 4, 2, 3}  # the five strongest of b
    common = sorted(top_a & top_b)
    direct = math.sqrt(sum((a[i] - b[i]) ** 2 for i in common)) / len(common)
    assert n == len(common) == 4
    assert sim == pytest.approx(direct)


def test_eq3_without_common_aps_is_no_encounter() -> None:
    a = np.array([-40.0, NAN])
    b = np.array([NAN, -40.0])
    assert wifi_eq3_similarity(a, b, WifiEq3Params()) == (math.inf, 0)


def test_strongest_ignores_unheard() -> None:
    rss = np.array([NAN, -70.0, -40.0, NAN, -55.0])
    assert strongest(rss, 2).tolist() == [2, 4]
    assert sorted(strongest(rss, 10).tolist()) == [1, 2, 4]


@pytest.mark.parametrize(("kind", "coef"), [("wifi-log", (1.0, 2.5)), ("bt-quadratic", (-60.0, -20.0, 0.8))])
def test_fit_recovers_a_known_model_and_inverts_it(kind: str, coef: tuple[float, ...]) -> None:
    rng = np.random.default_rng(0)
    d = rng.uniform(0.5, 30.0, 4000)
    truth = RangeModel(kind, coef, 1.0)
    feature = truth.feature_at(d) + rng.normal(0, 1.0, d.size)
    model = fit_range_model(feature, d, kind)
    np.testing.assert_allclose(model.coefficients, coef, atol=0.15)
    assert model.sigma == pytest.approx(1.0, abs=0.1)
    z, var = model.range_and_variance(truth.feature_at(np.array([2.0, 10.0])))
    np.testing.assert_allclose(z, [2.0, 10.0], rtol=0.1)
    assert var[0] < var[1]  # the feature changes fastest near: close ranges are the precise ones


def test_empirical_variance_is_a_floor() -> None:
    model = RangeModel("wifi-log", (1.0, 2.5), 0.5)
    feature = np.full(300, 3.0)  # the same reading at very different true distances
    distance = np.r_[np.full(150, 2.0), np.full(150, 20.0)]
    calibrated = model.with_empirical_variance(feature, distance)
    _, var_model = model.range_and_variance(np.array([3.0]))
    _, var_calibrated = calibrated.range_and_variance(np.array([3.0]))
    assert var_calibrated[0] > 10 * var_model[0]


def test_fit_needs_data_and_a_known_kind() -> None:
    with pytest.raises(ValueError, match="at least 10"):
        fit_range_model(np.ones(3), np.ones(3), "wifi-log")
    with pytest.raises(ValueError, match="valid: wifi-log, bt-quadratic"):
        fit_range_model(np.ones(30), np.ones(30), "cubic")
    with pytest.raises(ValueError, match="valid: wifi-eq3, wifi-fingerprint, bluetooth"):
        encounter_model("sonar")


@pytest.mark.parametrize(
    "model",
    [
        RangeModel("wifi-log", (0.0, 2.0), 3.0),
        RangeModel("bt-quadratic", (-60.0, -10.0, 0.0), 4.0),
        RangeModel("bt-quadratic", (-60.0, -22.0, 2.5), 4.0),  # a slope that flattens and turns
        RangeModel("wifi-log", (0.0, 2.0), 3.0, bin_edges=(0.0, 1.5, 3.0), bin_mse=(0.5, 30.0, 4.0)),
    ],
)
@pytest.mark.parametrize("max_sigma", [0.6, 2.0, 5.0, 50.0])
def test_no_distance_beyond_the_sigma_reach_passes(model: RangeModel, max_sigma: float) -> None:
    reach = model.sigma_reach(max_sigma, 8.0)
    d = np.linspace(0.0, 8.0, 800_001)  # a 10 um grid: 1,000 points between the reach's own
    passing = d[np.sqrt(model.variance_at_distance(d)) <= max_sigma]
    assert 0.0 <= reach <= 8.0
    if passing.size == 0:
        assert reach == 0.0
    else:
        assert passing.max() <= reach  # a bound: nothing passes beyond it
        assert reach - passing.max() <= 0.0101  # and a tight one
