"""``unique_ints`` and ``unique_ints_inverse`` against ``np.unique`` (their oracle), table and fallback; the
engine's slot check against the same oracle."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from slam_core.filter.dense_ids import (
    FINE,
    REPEATED,
    UNKNOWN,
    slots_problem,
    unique_ints,
    unique_ints_inverse,
)


def _check(values: np.ndarray) -> None:
    expected, expected_inverse = np.unique(values, return_inverse=True)
    found = unique_ints(values)
    uniques, inverse = unique_ints_inverse(values)
    for got in (found, uniques):
        assert got.dtype == values.dtype
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))
    np.testing.assert_array_equal(uniques[inverse], values)


@given(arrays(np.int64, st.integers(0, 300), elements=st.integers(0, 5_000)))
def test_small_ids_match_np_unique(values: np.ndarray) -> None:
    _check(values)


@given(arrays(np.int64, st.integers(1, 50), elements=st.integers(-(2**40), 2**40)))
def test_negative_or_sparse_values_match_np_unique(values: np.ndarray) -> None:
    _check(values)


@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.uint16])
def test_dtypes_and_edges(dtype: type) -> None:
    for values in ([], [0], [7, 7, 7], [3, 1, 2, 1, 3], [0, np.iinfo(dtype).max]):
        _check(np.array(values, dtype=dtype))
        _check(np.array(values * 40, dtype=dtype))  # long enough for the table


def test_non_integer_or_2d_input_is_refused() -> None:
    with pytest.raises(ValueError, match="1-D integer"):
        unique_ints(np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="1-D integer"):
        unique_ints_inverse(np.zeros((2, 2), dtype=np.int64))


@settings(deadline=None)  # the first example loads the compiled kernel
@given(
    arrays(np.int64, st.integers(0, 40), elements=st.integers(-3, 60)),
    arrays(np.bool_, 50),
    st.booleans(),
)
def test_the_slot_check_matches_its_oracle(slots: np.ndarray, active: np.ndarray, repeats: bool) -> None:
    """Unknown (out of range or inactive) before repeated, as ``DynamicSlam._check_users`` reports them; the
    marks of one call never count in the next (a stamp per call)."""
    seen = np.zeros(active.size, dtype=np.int64)
    for stamp in (1, 2):  # the same slots twice: the first call's marks must not make repeats
        known = all(0 <= u < active.size and active[u] for u in slots.tolist())
        expected = (
            UNKNOWN
            if not known
            else (REPEATED if not repeats and np.unique(slots).size < slots.size else FINE)
        )
        assert slots_problem(slots, active, seen, stamp, repeats) == expected


def test_the_engine_refuses_unknown_and_repeated_slots() -> None:
    from slam_core.filter.dynamic_slam import DynamicSlam
    from slam_core.filter.params import FilterParams

    engine = DynamicSlam(FilterParams(n_particles=8), initial_capacity=2)
    slots = [engine.add_user(float(k), 0.0) for k in range(3)]  # the state grows past its first capacity
    for users, message in (
        ([slots[0], slots[0]], "only once per call"),
        ([slots[2] + 1], "unknown user slot"),
    ):
        offsets = np.arange(len(users) + 1, dtype=np.int64)
        lengths, headings = np.full(len(users), 0.5), np.zeros(len(users))
        with pytest.raises(ValueError, match=message):
            engine.step(np.array(users, dtype=np.int64), offsets, lengths, headings)
    engine.step(np.array(slots, dtype=np.int64), np.arange(4, dtype=np.int64), np.full(3, 0.5), np.zeros(3))
