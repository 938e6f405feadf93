"""Encounters chosen on the filters' prediction: the rule's gates, its cooldown, and why it exists (readings
chosen on their own value are biased; readings chosen on the prediction are not)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from slam_core.encounters.models import RangeModel, fit_range_model
from slam_core.encounters.selection import (
    EncounterSelector,
    SelectionParams,
    latest_per_pair,
    pair_key,
    pair_keys,
)

PHYSICAL_BT = RangeModel("bt-quadratic", (-60.0, -22.0 / math.log(10.0), 0.0), 2.8)


def _choose(selector: EncounterSelector, t_ms: list[int], keys: list[tuple[str, str, int]], d: list[float]):  # type: ignore[no-untyped-def]
    predicted = np.array(d, dtype=float)
    sigma = np.sqrt(PHYSICAL_BT.variance_at_distance(predicted))
    return selector.choose(np.array(t_ms, dtype=np.int64), keys, predicted, sigma)


def test_pairs_placed_close_are_chosen_far_ones_are_not() -> None:
    selector = EncounterSelector(SelectionParams(select_range_m=8.0, max_sigma_m=5.0))
    keys = [pair_key("a", "b", 1), pair_key("c", "d", 1)]
    chosen = _choose(selector, [0, 0], keys, [3.0, 20.0])
    assert chosen.tolist() == [True, False]
    assert selector.n_considered == 2
    assert selector.n_chosen == 1


def test_an_uninformative_model_is_not_chosen_even_close() -> None:
    selector = EncounterSelector(SelectionParams(select_range_m=8.0, max_sigma_m=1.0))
    # the physical model's range sigma is 2.8 dB / (22 dB per decade) * d ln 10: 1.4 m at 5 m, 0.6 m at 2 m
    chosen = _choose(selector, [0, 0], [pair_key("a", "b", 1), pair_key("c", "d", 1)], [2.0, 5.0])
    assert chosen.tolist() == [True, False]


def test_a_pair_cools_down_per_model_and_in_either_order() -> None:
    selector = EncounterSelector(SelectionParams(pair_cooldown_ms=5_000))
    assert pair_key("b", "a", 1) == pair_key("a", "b", 1) == ("a", "b", 1)
    assert _choose(selector, [1_000], [pair_key("a", "b", 1)], [3.0]).tolist() == [True]
    assert _choose(selector, [4_000], [pair_key("b", "a", 1)], [3.0]).tolist() == [False]
    assert _choose(selector, [4_000], [pair_key("b", "a", 0)], [3.0]).tolist() == [True]  # other model
    assert _choose(selector, [6_000], [pair_key("a", "b", 1)], [3.0]).tolist() == [True]
    # a pair placed too far does not start a cooldown
    assert _choose(selector, [20_000], [pair_key("a", "b", 1)], [30.0]).tolist() == [False]
    assert _choose(selector, [20_500], [pair_key("a", "b", 1)], [3.0]).tolist() == [True]


def test_the_pairs_latest_reading_of_a_call_is_the_one_considered() -> None:
    selector = EncounterSelector(SelectionParams())
    keys = [pair_key("a", "b", 1)] * 3
    assert _choose(selector, [300, 900, 100], keys, [3.0, 3.0, 3.0]).tolist() == [False, True, False]


def test_forgetting_keeps_running_cooldowns() -> None:
    selector = EncounterSelector(SelectionParams(pair_cooldown_ms=5_000))
    _choose(selector, [0, 9_000], [pair_key("a", "b", 1), pair_key("c", "d", 1)], [3.0, 3.0])
    assert len(selector) == 2
    selector.forget_before(10_000)
    assert len(selector) == 1
    assert _choose(selector, [10_000], [pair_key("c", "d", 1)], [3.0]).tolist() == [False]


def test_bad_arguments_are_refused() -> None:
    selector = EncounterSelector(SelectionParams())
    with pytest.raises(ValueError, match="equally long"):
        selector.choose(np.zeros(2, dtype=np.int64), [pair_key("a", "b", 1)], np.ones(2), np.ones(2))
    with pytest.raises(ValueError, match="finite"):
        selector.choose(
            np.zeros(1, dtype=np.int64), [pair_key("a", "b", 1)], np.array([math.nan]), np.ones(1)
        )
    for bad in ({"select_range_m": 0.0}, {"max_sigma_m": -1.0}, {"pair_cooldown_ms": -1}):
        with pytest.raises(ValueError, match="must be"):
            SelectionParams(**bad)  # type: ignore[arg-type]


def test_readings_chosen_on_the_prediction_are_unbiased_those_chosen_on_their_value_are_not() -> None:
    """Far pairs outnumber close ones: among readings that *look* close, many are far pairs read strong by
    chance, so their reported range is short of the truth. Choosing on the filters' prediction (truth plus
    the filters' own error, independent of the reading's noise) keeps the reading's noise unbiased."""
    rng = np.random.default_rng(3)
    true = rng.uniform(0.5, 30.0, 200_000)  # pairs spread over the floor
    rss = PHYSICAL_BT.feature_at(true) + rng.normal(0.0, 2.8, true.size)
    reported, _ = PHYSICAL_BT.range_and_variance(rss)
    by_value = reported <= 8.0
    by_prediction = np.hypot(*(rng.normal(0.0, 1.0, (2, true.size)))) + true <= 8.0
    log_error_by_value = np.median(np.log(reported[by_value] / true[by_value]))
    log_error_by_prediction = np.median(np.log(reported[by_prediction] / true[by_prediction]))
    assert log_error_by_value < -0.06  # about 9 % short
    assert abs(log_error_by_prediction) < 0.02  # 0.3 %


def test_variance_at_the_reported_range_is_the_readings_r() -> None:
    model = PHYSICAL_BT.with_empirical_variance(
        PHYSICAL_BT.feature_at(np.array([1.0, 2.0, 5.0] * 20)), np.array([1.2, 2.5, 4.0] * 20)
    )
    feature = np.array([-60.0, -70.0, -80.0, -90.0])
    d, r = model.range_and_variance(feature)
    np.testing.assert_allclose(model.variance_at_distance(d), r)
    # analytic part: (sigma / |f'(d)|)^2 grows with distance, floored at 0.25 m^2
    plain = PHYSICAL_BT.variance_at_distance(np.array([1.0, 5.0, 20.0]))
    slope = 22.0 / (np.array([1.0, 5.0, 20.0]) * math.log(10.0))
    np.testing.assert_allclose(plain, np.maximum((2.8 / slope) ** 2, 0.25), rtol=0.02)


def test_fitting_where_the_model_is_used_avoids_the_sensitivity_cut() -> None:
    """Beyond the receiver's sensitivity only lucky strong readings are heard: fitted over all distances,
    they flatten the model; fitted up to 25 m, it is the true one."""
    rng = np.random.default_rng(0)
    true = rng.uniform(0.5, 60.0, 50_000)
    rss = PHYSICAL_BT.feature_at(true) + rng.normal(0.0, 4.0, true.size)
    heard = rss >= -95.0
    everywhere = fit_range_model(rss[heard], true[heard], "bt-quadratic")
    near = fit_range_model(rss[heard], true[heard], "bt-quadratic", max_distance_m=25.0)
    grid = np.array([2.0, 5.0, 10.0, 15.0])  # where encounters are used
    truth = PHYSICAL_BT.feature_at(grid)
    assert np.max(np.abs(near.feature_at(grid) - truth)) < 0.45  # 0.27-0.32 dB over seeds 0-3
    assert np.max(np.abs(everywhere.feature_at(grid) - truth)) > 0.65  # 0.79-0.82 dB


@pytest.mark.parametrize("seed", range(4))
def test_the_latest_readings_are_those_of_a_sort_by_time(seed: int) -> None:
    """Random readings (times with many ties, keys repeated, large pair keys): the hash table's choice is the
    sort's (each key's first in the readings sorted latest first, ties latest index first)."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3_000))
    t = rng.integers(0, 50, n).astype(np.int64) + 1_700_000_000_000
    keys = rng.choice(rng.integers(0, 2**60, 200), n).astype(np.int64)
    backwards = np.argsort(t, kind="stable")[::-1]
    _, first = np.unique(keys[backwards], return_index=True)
    assert latest_per_pair(t, keys).tolist() == np.sort(backwards[first]).tolist()


def test_each_pairs_latest_reading_is_found_and_the_last_of_equal_times() -> None:
    t = np.array([5, 9, 7, 9, 1, 3], dtype=np.int64)
    keys = np.array([10, 10, 20, 10, 30, 20], dtype=np.int64)
    assert latest_per_pair(t, keys).tolist() == [2, 3, 4]  # pair 10 read twice at 9: its last reading
    assert latest_per_pair(np.zeros(0, np.int64), np.zeros(0, np.int64)).tolist() == []
    # choose considers exactly these: narrowing its input to them changes nothing
    predicted = np.array([3.0, 3.0, 30.0, 4.0, 2.0, 3.0])
    sigma = np.sqrt(PHYSICAL_BT.variance_at_distance(predicted))
    whole = EncounterSelector(SelectionParams()).choose(t, keys, predicted, sigma)
    latest = latest_per_pair(t, keys)
    narrowed = EncounterSelector(SelectionParams()).choose(
        t[latest], keys[latest], predicted[latest], sigma[latest]
    )
    assert np.flatnonzero(whole).tolist() == latest[narrowed].tolist() == [3, 4]


def test_a_user_in_a_crowd_takes_its_nearest_peers_and_then_one_a_second() -> None:
    """A user within range of many peers takes at most ``user_burst`` at once, the most informative
    (nearest predicted) first, then ``user_rate_per_s`` a second; its peers' allowances are their own."""
    selector = EncounterSelector(SelectionParams(user_rate_per_s=1.0, user_burst=3.0))
    peers = [f"p{k}" for k in range(8)]
    distances = [7.0, 1.0, 6.0, 2.0, 5.0, 3.0, 4.0, 7.5]
    keys = [pair_key("me", p, 1) for p in peers]
    predicted = np.array(distances)
    sigma = np.sqrt(PHYSICAL_BT.variance_at_distance(predicted))
    users = (["me"] * 8, peers)
    first = selector.choose(np.zeros(8, dtype=np.int64), keys, predicted, sigma, users)
    assert [p for p, c in zip(peers, first, strict=True) if c] == ["p1", "p3", "p5"]  # 1, 2 and 3 m away
    # a second later the allowance holds one more: the nearest of those not in their pair's cooldown
    again = selector.choose(np.full(8, 1_000, dtype=np.int64), keys, predicted, sigma, users)
    assert [p for p, c in zip(peers, again, strict=True) if c] == ["p6"]
    # two strangers are not held back by this user's allowance
    other = selector.choose(
        np.array([1_000]), [pair_key("x", "y", 1)], np.array([2.0]), sigma[:1], (["x"], ["y"])
    )
    assert other.tolist() == [True]
    # without users (a caller that names none) only the pair cooldown applies
    free = EncounterSelector(SelectionParams(user_rate_per_s=1.0, user_burst=1.0))
    assert free.choose(np.zeros(8, dtype=np.int64), keys, predicted, sigma).sum() == 8
    with pytest.raises(ValueError, match="user_rate_per_s"):
        SelectionParams(user_rate_per_s=0.0)


class _ReferenceSelector:
    """The oracle: the selector's rule as plain Python over dictionaries, one reading at a time."""

    def __init__(self, params: SelectionParams) -> None:
        self.params = params
        self.last: dict[int, int] = {}
        self.tokens: dict[int, tuple[float, int]] = {}

    def allowance(self, user: int, t: int) -> float:
        p = self.params
        held = self.tokens.get(user)
        if held is None:
            return p.user_burst
        left, since = held
        return min(p.user_burst, left + max(t - since, 0) * p.user_rate_per_s / 1e3)

    def choose(self, t_ms, keys, predicted, sigma, users):  # type: ignore[no-untyped-def]
        p = self.params
        chosen = np.zeros(t_ms.size, dtype=bool)
        latest = latest_per_pair(t_ms, keys)
        gated = latest[(predicted[latest] <= p.select_range_m) & (sigma[latest] <= p.max_sigma_m)]
        gated = gated[np.argsort(sigma[gated], kind="stable")]
        for i in gated.tolist():
            key, t = int(keys[i]), int(t_ms[i])
            if key in self.last and t - self.last[key] < p.pair_cooldown_ms:
                continue
            a, b = int(users[0][i]), int(users[1][i])
            left = (self.allowance(a, t), self.allowance(b, t))
            if min(left) < 1.0:
                continue
            self.tokens[a], self.tokens[b] = (left[0] - 1.0, t), (left[1] - 1.0, t)
            self.last[key] = t
            chosen[i] = True
        return chosen

    def forget_before(self, t_ms: int) -> None:
        p = self.params
        self.last = {k: v for k, v in self.last.items() if v >= t_ms - p.pair_cooldown_ms}
        full = t_ms - p.user_burst / p.user_rate_per_s * 1e3
        self.tokens = {k: v for k, v in self.tokens.items() if v[1] >= full}


@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_cooldowns_choose_what_the_rule_read_one_reading_at_a_time_chooses(seed: int) -> None:
    """Many calls of a busy building (readings of 60 users, out of order within a call, the table growing
    past its first size, pickled as a snapshot would and forgotten now and then): the same choices, the same
    allowances, the same pairs remembered."""
    rng = np.random.default_rng(seed)
    params = SelectionParams(
        user_rate_per_s=[1.0, 0.7, 2.0, 1.0][seed], user_burst=[3.0, 1.0, 2.5, 3.0][seed]
    )
    compiled, reference = EncounterSelector(params), _ReferenceSelector(params)
    t0 = 1_796_559_880_000
    for call in range(120):
        n = int(rng.integers(0, 400))
        a, b = rng.integers(0, 60, n), rng.integers(0, 60, n)
        b = np.where(a == b, (b + 1) % 60, b)
        keys = pair_keys(a, b, rng.integers(0, 2, n))
        t = t0 + 1_000 * call + rng.integers(-900, 900, n)
        predicted = rng.uniform(0.0, 12.0, n)
        sigma = rng.uniform(0.5, 6.0, n)
        got = compiled.choose(t, keys, predicted, sigma, (a, b))
        want = reference.choose(t, keys, predicted, sigma, (a, b))
        assert got.tolist() == want.tolist(), call
        assert len(compiled) == len(reference.last)
        if call % 37 == 36:
            compiled = pickle.loads(pickle.dumps(compiled))
        if call % 25 == 24:
            compiled.forget_before(int(t.max()) if n else t0 + 1_000 * call)
            reference.forget_before(int(t.max()) if n else t0 + 1_000 * call)
            assert len(compiled) == len(reference.last)
    assert compiled.n_chosen > 100  # the cooldowns and allowances were exercised, not only the gates
