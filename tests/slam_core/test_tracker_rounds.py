"""A user's dead-reckoned trail: what ``at`` answers against a plain list of the steps laid, the window it
keeps, and a pickle round trip (snapshots) that restores it exactly."""

from __future__ import annotations

import math
import pickle

import numpy as np

from slam_core.tracker_rounds import TRAIL_MS, UserTrack


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
    track, _ = _walk(20)
    track.origin = np.array([3.0, 4.0])
    restored = pickle.loads(pickle.dumps(track, protocol=pickle.HIGHEST_PROTOCOL))
    assert restored.trail == track.trail
    for name in UserTrack._VECTORS:
        got, want = getattr(restored, name), getattr(track, name)
        assert got.dtype == np.float64
        assert np.array_equal(got, want)
    assert (restored.walked, restored.last_t_ms, restored.number) == (track.walked, track.last_t_ms, -1)
    restored.lay([99_000], [1.0], [0.0], [1.0], (1.0, 0.0), (1.0, 0.0), math.nan)  # still a live track
    assert restored.displacement[0] == track.displacement[0] + 1.0
