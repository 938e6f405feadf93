"""The filter state's pickled form (the server's snapshots) and its slot allocator."""

from __future__ import annotations

import pickle
from dataclasses import fields

import numpy as np
import pytest

from slam_core.filter.state import NO_CROWD_ID, FilterState, SlotAllocator


def _state_with_maps(rng: np.random.Generator) -> FilterState:
    state = FilterState.empty(capacity=8, n_particles=5, map_capacity=12)
    for f in fields(state):
        array = getattr(state, f.name)
        if array.dtype == np.bool_:
            array[...] = rng.random(array.shape) < 0.5
        elif np.issubdtype(array.dtype, np.integer):
            array[...] = rng.integers(0, 7, array.shape)
        else:
            array[...] = rng.normal(size=array.shape)
    state.map_n[...] = rng.integers(0, 4, state.map_n.shape)  # at most 3 of the 12 map entries in use
    state.map_n[2, 3] = 4
    return state


def test_a_pickled_state_keeps_every_array_up_to_the_longest_map_and_defaults_past_it() -> None:
    state = _state_with_maps(np.random.default_rng(0))
    restored = pickle.loads(pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL))
    empty = FilterState.empty(8, 5, 12)
    for f in fields(state):
        before, after = getattr(state, f.name), getattr(restored, f.name)
        assert after.shape == before.shape, f.name
        assert after.dtype == before.dtype, f.name
        if before.ndim >= 3 and before.shape[2] == 12:  # a per-particle map array
            np.testing.assert_array_equal(after[:, :, :4], before[:, :, :4], err_msg=f.name)
            np.testing.assert_array_equal(after[:, :, 4:], getattr(empty, f.name)[:, :, 4:], err_msg=f.name)
        else:
            np.testing.assert_array_equal(after, before, err_msg=f.name)
    assert np.all(restored.map_crowd_id[:, :, 4:] == NO_CROWD_ID)
    restored.map_mu[0, 0, 0, 0] = 1e9  # a copy, not a view of the original
    assert state.map_mu[0, 0, 0, 0] != 1e9


def test_a_pickled_state_costs_its_used_map_entries_not_its_capacity() -> None:
    state = FilterState.empty(capacity=256, n_particles=75, map_capacity=48)
    empty_size = len(pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL))
    state.map_n[0, :] = 2
    two_anchor_size = len(pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL))
    full_maps = sum(getattr(state, name).nbytes for name in ("map_mu", "map_cov", "map_crowd_id"))
    assert empty_size < full_maps / 20
    per_anchor_column = 256 * 75 * (16 + 24 + 1 + 4 + 1 + 8)
    assert two_anchor_size - empty_size == pytest.approx(2 * per_anchor_column, rel=0.01)


def test_slots_are_reused_and_the_arrays_grow_by_doubling() -> None:
    slots = SlotAllocator(2)
    assert slots.allocate() == (0, None)
    assert slots.allocate() == (1, None)
    assert slots.allocate() == (2, 4)
    slots.release(0)
    assert slots.allocate() == (0, None)
    slots.release(2)
    with pytest.raises(ValueError, match="slot 2 is not allocated"):
        slots.release(2)
    with pytest.raises(ValueError, match="slot 4 is not allocated"):
        slots.release(4)
    state = FilterState.empty(2, 3, 4)
    state.x[1] = 5.0
    grown = state.grown(4)
    assert grown.capacity == 4
    assert np.all(grown.x[1] == 5.0)
    assert np.all(grown.x[2:] == 0.0)
