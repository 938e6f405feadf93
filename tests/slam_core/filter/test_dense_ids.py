"""``unique_ints`` and ``unique_ints_inverse`` against ``np.unique`` (their oracle), table and fallback."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from slam_core.filter.dense_ids import unique_ints, unique_ints_inverse


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
