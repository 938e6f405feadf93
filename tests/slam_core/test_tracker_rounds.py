"""A user's dead-reckoned trail: what ``at`` answers against a plain list of the steps laid, the window it
keeps, and a pickle round trip (snapshots) that restores it exactly."""

from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np

from slam_core.tracker_rounds import TRAIL_MS, UserTrack, carried_since, carry_variance, trail_lookup


def _walk(seconds: int) -> tuple[UserTrack, list[tuple[int, float, float, float]]]:
    """Two steps a second; returns the track and every step as (t, x, y, walked) after it."""
    rng = np.random.default_rng(3)
    track, steps = UserTrack(), []
    x = y = walked = 0.0
    for second in range(seconds):
        times = [second * 1_000 + 500, second * 1_000 + 1_000]
        dx, dy = rng.normal(0.0, 0.5, 2).tolist(), rng.normal(0.0, 0.5, 2).tolist()
        lengths = [math.hypot(a, b) for a, b in zip(dx, dy, strict=True)]
        track.lay(times, dx, dy, lengths, (sum(dx), sum(dy)), (sum(dx), sum(dy)), math.nan)
        track.last_t_ms = times[-1]
        for t, a, b, length in zip(times, dx, dy, lengths, strict=True):
            x, y, walked = x + a, y + b, walked + length
            steps.append((t, x, y, walked))
    return track, steps


def test_the_trail_answers_the_last_step_at_or_before_a_time_within_its_window() -> None:
    track, steps = _walk(60)
    kept = [s for s in steps if s[0] >= steps[-1][0] - TRAIL_MS]
    assert len(track.trail) == 4 * len(kept)
    for t, x, y, walked in kept:
        for query in (t, t + 250):
            displacement, distance = track.at(query)
            assert np.allclose(displacement, [x, y], atol=1e-9)
            assert math.isclose(distance, walked)
    # older than the window: the oldest step kept; after the last step: where the user is now
    oldest, now = track.at(0), track.at(steps[-1][0] + 10_000)
    assert np.allclose(oldest[0], kept[0][1:3])
    assert math.isclose(oldest[1], kept[0][3])
    assert np.array_equal(now[0], track.displacement)
    assert now[1] == track.walked
    assert np.allclose(track.displacement, steps[-1][1:3], atol=1e-9)


def test_a_pickled_track_is_restored_exactly() -> None:
    """Every field survives (one forgotten by ``__getstate__``, which lists them by hand, fails here)."""
    track, _ = _walk(20)
    track.origin = np.array([3.0, 4.0])
    track.number, track.slot, track.heading, track.heading_offset = 7, 3, 0.25, -0.125
    track.since_gyro, track.since_laid = np.array([0.5, -1.5]), np.array([2.5, 3.5])
    track.gyro_displacement = np.array([-4.0, 8.0])
    restored = pickle.loads(pickle.dumps(track, protocol=pickle.HIGHEST_PROTOCOL))
    for f in dataclasses.fields(UserTrack):
        got, want = getattr(restored, f.name), getattr(track, f.name)
        if f.name in UserTrack._VECTORS:
            assert got.dtype == np.float64
            assert np.array_equal(got, want), f.name
        else:
            assert got == want, f.name
            assert want != getattr(UserTrack(), f.name), f"set {f.name} in this test"
    restored.lay([99_000], [1.0], [0.0], [1.0], (1.0, 0.0), (1.0, 0.0), math.nan)  # still a live track
    assert restored.displacement[0] == track.displacement[0] + 1.0


def test_a_track_pickled_before_the_flat_tuple_is_restored() -> None:
    """Snapshots written before users travelled as flat tuples (a dict of fields, 2-vectors as tuples) still
    load: the snapshot format did not change."""
    track, _ = _walk(5)
    old_state = dict(track.__dict__)
    for name in UserTrack._VECTORS:
        old_state[name] = tuple(old_state[name].tolist())
    restored = UserTrack.__new__(UserTrack)
    restored.__setstate__(old_state)
    assert restored.trail == track.trail
    assert restored.last_t_ms == track.last_t_ms
    for name in UserTrack._VECTORS:
        assert getattr(restored, name).dtype == np.float64
        assert np.array_equal(getattr(restored, name), getattr(track, name), equal_nan=True), name


def _at_by_hand(track: UserTrack, t_ms: int) -> tuple[tuple[float, float], float]:
    """``at`` as its docstring says it, from the trail as a plain list."""
    rows = [track.trail[i : i + 4].tolist() for i in range(0, len(track.trail), 4)]
    before = [r for r in rows if r[0] <= t_ms]
    if before:
        return (before[-1][1], before[-1][2]), before[-1][3]
    if not rows or t_ms >= track.last_t_ms:
        return (float(track.displacement[0]), float(track.displacement[1])), track.walked
    return (rows[0][1], rows[0][2]), rows[0][3]


def test_many_users_times_at_once_answer_as_one_at_a_time() -> None:
    """``trail_lookup`` searches several users' trails in one pass: each answer is the user's own, at a
    time inside, before and after its trail, and for a user with no steps yet."""
    long, _ = _walk(60)
    short, steps = _walk(3)
    empty = UserTrack()
    empty.displacement = np.array([5.0, 6.0])
    tracks = [long, empty, short]
    times = [0, 500, 31_000, 45_250, 60_000, 70_000, steps[0][0] - 1, steps[1][0]]
    which = np.array([w for w in range(3) for _ in times], dtype=np.int64)
    t = np.array(times * 3, dtype=np.int64)
    displacement, walked = trail_lookup(tracks, which, t)
    for k, (w, query) in enumerate(zip(which.tolist(), t.tolist(), strict=True)):
        (x, y), distance = _at_by_hand(tracks[w], query)
        assert displacement[k].tolist() == [x, y], (w, query)
        assert walked[k] == distance
        one, one_walked = tracks[w].at(query)
        assert one.tolist() == [x, y]
        assert one_walked == distance
    long.lay([99_000], [1.0], [0.0], [1.0], (1.0, 0.0), (1.0, 0.0), math.nan)  # the trails still grow


def test_carrying_a_time_to_now_follows_the_steps_since_and_grows_with_the_distance() -> None:
    track, steps = _walk(60)
    t = np.array([steps[-3][0], steps[-1][0], steps[-1][0] - TRAIL_MS - 1], dtype=np.int64)
    shift, walked, placeable = carried_since([track], np.zeros(3, np.int64), t)
    assert np.allclose(shift[0], np.array(steps[-1][1:3]) - np.array(steps[-3][1:3]), atol=1e-9)
    assert np.array_equal(shift[1], np.zeros(2))
    assert walked[1] == 0.0
    assert math.isclose(walked[0], steps[-1][3] - steps[-3][3])
    assert math.isclose(float(carry_variance(walked[0])), (0.1 * walked[0]) ** 2)
    assert placeable.tolist() == [True, True, False]  # older than the trail cannot be carried
