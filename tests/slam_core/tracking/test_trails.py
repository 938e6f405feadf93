"""A user's dead-reckoned trail: what ``trail_lookup`` answers against a plain list of the steps laid, the
window it keeps, the pool of trails as slots come and go, a pickle round trip (snapshots) that restores
it exactly, and readings placed in time (``slam_core.tracking.carry``: carried back, guessed ahead)."""

from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np
import pytest

from slam_core.tracking.carry import SlotColumns, carried_since, carry_variance, trail_lookup
from slam_core.tracking.trails import MAX_SPEED_M_PER_MS, TRAIL_MS, Trails, UserTrack


def _lookup(
    trails: Trails, tracks: list[UserTrack], which: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``trail_lookup`` of ``tracks[which[i]]`` at ``t[i]``, with the tracks' own columns."""
    return trail_lookup(
        trails,
        np.array([u.slot for u in tracks], dtype=np.int64)[which],
        t,
        np.array([u.last_t_ms for u in tracks], dtype=np.int64)[which],
        np.array([u.displacement for u in tracks]).reshape(-1, 2)[which],
        np.array([u.walked for u in tracks])[which],
    )


def _at(trails: Trails, track: UserTrack, t_ms: int) -> tuple[np.ndarray, float]:
    """One user's ``trail_lookup`` at one time."""
    displacement, walked = _lookup(trails, [track], np.zeros(1, np.int64), np.array([t_ms]))
    return displacement[0], float(walked[0])


def _rows(trails: Trails, track: UserTrack) -> list[list[float]]:
    return trails.of(track.slot).tolist()


def _walk(
    seconds: int, slot: int = 0, trails: Trails | None = None, seed: int = 3
) -> tuple[UserTrack, Trails, list[tuple[int, float, float, float]]]:
    """Two steps a second; returns the track, its trails and every step as (t, x, y, walked) after it."""
    rng = np.random.default_rng(seed)
    trails = Trails() if trails is None else trails
    trails.reset(slot)
    track, steps = UserTrack(slot=slot), []
    x = y = walked = 0.0
    for second in range(seconds):
        times = [second * 1_000 + 500, second * 1_000 + 1_000]
        dx, dy = rng.normal(0.0, 0.5, 2).tolist(), rng.normal(0.0, 0.5, 2).tolist()
        lengths = [math.hypot(a, b) for a, b in zip(dx, dy, strict=True)]
        track.lay(trails, times, dx, dy, lengths, (sum(dx), sum(dy)), (sum(dx), sum(dy)), math.nan)
        track.last_t_ms = times[-1]
        for t, a, b, length in zip(times, dx, dy, lengths, strict=True):
            x, y, walked = x + a, y + b, walked + length
            steps.append((t, x, y, walked))
    return track, trails, steps


def test_the_trail_answers_the_last_step_at_or_before_a_time_within_its_window() -> None:
    track, trails, steps = _walk(60)
    kept = [s for s in steps if s[0] >= steps[-1][0] - TRAIL_MS]
    assert len(_rows(trails, track)) == len(kept)
    for t, x, y, walked in kept:
        for query in (t, t + 250):
            displacement, distance = _at(trails, track, query)
            assert np.allclose(displacement, [x, y], atol=1e-9)
            assert math.isclose(distance, walked)
    # older than the window: the oldest step kept; after the last step: where the user is now
    oldest, now = _at(trails, track, 0), _at(trails, track, steps[-1][0] + 10_000)
    assert np.allclose(oldest[0], kept[0][1:3])
    assert math.isclose(oldest[1], kept[0][3])
    assert np.array_equal(now[0], track.displacement)
    assert now[1] == track.walked
    assert np.allclose(track.displacement, steps[-1][1:3], atol=1e-9)


VECTORS = ("displacement", "origin", "gyro_displacement", "since_gyro", "since_laid")
"""The track's 2-vectors, which travel as plain floats in a snapshot."""


def test_a_pickled_track_is_restored_exactly() -> None:
    """Every field survives (one forgotten by ``__getstate__``, which lists them by hand, fails here), and
    the trails' pool with it."""
    track, trails, _ = _walk(20)
    track.origin = np.array([3.0, 4.0])
    track.number, track.heading, track.heading_offset = 7, 0.25, -0.125
    track.since_gyro, track.since_laid = np.array([0.5, -1.5]), np.array([2.5, 3.5])
    track.gyro_displacement = np.array([-4.0, 8.0])
    track.placed = False
    track.slot = 3
    trails.reset(3)
    restored, restored_trails = pickle.loads(pickle.dumps((track, trails), protocol=pickle.HIGHEST_PROTOCOL))
    assert _rows(restored_trails, restored) == _rows(trails, track) == []
    assert restored_trails.of(0).tolist() == trails.of(0).tolist() != []
    for f in dataclasses.fields(UserTrack):
        got, want = getattr(restored, f.name), getattr(track, f.name)
        if f.name in VECTORS:
            assert got.dtype == np.float64
            assert np.array_equal(got, want), f.name
        else:
            assert got == want, f.name
            assert want != getattr(UserTrack(), f.name), f"set {f.name} in this test"
    restored.lay(restored_trails, [99_000], [1.0], [0.0], [1.0], (1.0, 0.0), (1.0, 0.0), math.nan)
    assert restored.displacement[0] == track.displacement[0] + 1.0  # still a live track
    assert _rows(restored_trails, restored) == [[99_000.0, *restored.displacement.tolist(), restored.walked]]


def _at_by_hand(trails: Trails, track: UserTrack, t_ms: int) -> tuple[tuple[float, float], float]:
    """``at`` as its docstring says it, from the trail as a plain list."""
    rows = _rows(trails, track)
    before = [r for r in rows if r[0] <= t_ms]
    if before:
        return (before[-1][1], before[-1][2]), before[-1][3]
    if not rows or t_ms >= track.last_t_ms:
        return (float(track.displacement[0]), float(track.displacement[1])), track.walked
    return (rows[0][1], rows[0][2]), rows[0][3]


def test_many_users_times_at_once_answer_as_one_at_a_time() -> None:
    """``trail_lookup`` searches several users' trails in one pass: each answer is the user's own, at a
    time inside, before and after its trail, and for a user with no steps yet."""
    long, trails, _ = _walk(60, slot=2)
    short, _, steps = _walk(3, slot=0, trails=trails)
    empty = UserTrack(slot=5)
    trails.reset(5)
    empty.displacement = np.array([5.0, 6.0])
    tracks = [long, empty, short]
    times = [0, 500, 31_000, 45_250, 60_000, 70_000, steps[0][0] - 1, steps[1][0]]
    which = np.array([w for w in range(3) for _ in times], dtype=np.int64)
    t = np.array(times * 3, dtype=np.int64)
    displacement, walked = _lookup(trails, tracks, which, t)
    for k, (w, query) in enumerate(zip(which.tolist(), t.tolist(), strict=True)):
        (x, y), distance = _at_by_hand(trails, tracks[w], query)
        assert displacement[k].tolist() == [x, y], (w, query)
        assert walked[k] == distance
        one, one_walked = _at(trails, tracks[w], query)
        assert one.tolist() == [x, y]
        assert one_walked == distance
    long.lay(trails, [99_000], [1.0], [0.0], [1.0], (1.0, 0.0), (1.0, 0.0), math.nan)  # the trails still grow


def test_the_pool_keeps_every_slots_trail_as_slots_come_go_and_restart() -> None:
    """Slots laid in turn, released, reused and restarted, through the pool's moves and compactions: every
    live slot's rows are its own walk's last ``TRAIL_MS``, as a trail of its own would hold them."""
    trails = Trails()
    rng = np.random.default_rng(0)
    own: dict[int, list[list[float]]] = {}
    walked = dict.fromkeys(range(40), 0.0)
    for second in range(120):
        for slot in rng.choice(40, 15, replace=False).tolist():
            if slot not in own:
                trails.reset(slot)
                own[slot], walked[slot] = [], 0.0
            n = int(rng.integers(1, 6))
            times = [second * 1_000 + 100 * k for k in range(1, n + 1)]
            rows = []
            for t in times:
                walked[slot] += 0.7
                rows.append([float(t), float(slot), float(t) / 7.0, walked[slot]])
            trails.lay(slot, [v for row in rows for v in row], times[-1] - TRAIL_MS)
            own[slot] = [r for r in own[slot] + rows if r[0] >= times[-1] - TRAIL_MS]
        gone = int(rng.integers(0, 40))
        if gone in own and rng.random() < 0.3:  # a user leaves (its slot freed) or restarts its timeline
            if rng.random() < 0.5:
                trails.release(gone)
            else:
                trails.reset(gone)
            del own[gone]
        if second % 37 == 0:
            trails = pickle.loads(pickle.dumps(trails))
        for slot, rows in own.items():
            assert trails.of(slot).tolist() == rows, (second, slot)
    assert trails.rows.shape[0] < 4 * sum(int(c) for c in trails.capacity) + 512  # waste is reclaimed


def test_carrying_a_time_to_now_follows_the_steps_since_and_grows_with_the_distance() -> None:
    track, trails, steps = _walk(60)
    t = np.array([steps[-3][0], steps[-1][0], steps[-1][0] - TRAIL_MS - 1], dtype=np.int64)
    shift, walked, placeable = carried_since(trails, np.zeros(3, np.int64), np.full(3, track.last_t_ms), t)
    assert np.allclose(shift[0], np.array(steps[-1][1:3]) - np.array(steps[-3][1:3]), atol=1e-9)
    assert np.array_equal(shift[1], np.zeros(2))
    assert walked[1] == 0.0
    assert math.isclose(walked[0], steps[-1][3] - steps[-3][3])
    assert math.isclose(float(carry_variance(walked[0])), (0.1 * walked[0]) ** 2)
    assert placeable.tolist() == [True, True, False]  # older than the trail cannot be carried


def _east(trails: Trails, slot: int, speed_m_per_s: float) -> UserTrack:
    """Ten seconds of steps east, two a second, at ``speed_m_per_s``."""
    track = UserTrack(slot=slot)
    trails.reset(slot)
    step = speed_m_per_s / 2.0
    for second in range(10):
        times = [second * 1_000 + 500, second * 1_000 + 1_000]
        track.lay(
            trails, times, [step, step], [0.0, 0.0], [step, step], (2 * step, 0.0), (2 * step, 0.0), math.nan
        )
        track.last_t_ms = times[-1]
    return track


def test_a_lagging_user_is_guessed_ahead_at_its_recent_velocity_capped_at_a_run() -> None:
    trails = Trails()
    walker, runner, standing = _east(trails, 0, 1.4), _east(trails, 1, 5.0), UserTrack(slot=2)
    trails.reset(2)
    standing.last_t_ms = 1_000
    columns = SlotColumns()
    for track in (walker, runner, standing):
        columns.reset(track.slot)
    columns.update([walker, runner, standing], [10_000, 10_000, 1_000], trails)
    slots = np.array([0, 0, 0, 1, 2, 0])
    t = np.array([10_500, 9_000, 10_000, 11_000, 5_000, 16_000], dtype=np.int64)
    ahead, variance, heard = columns.extrapolated(slots, t)
    np.testing.assert_allclose(ahead[0], [0.7, 0.0], atol=1e-12)  # half a second at 1.4 m/s
    assert math.isclose(variance[0], 0.25 * 0.7**2)
    assert ahead[1:3].tolist() == [[0.0, 0.0], [0.0, 0.0]]  # not after its last report: nothing to guess
    assert variance[1] == variance[2] == 0.0
    np.testing.assert_allclose(ahead[3], [1000 * MAX_SPEED_M_PER_MS, 0.0], atol=1e-12)  # 3 m in 1 s, not 5
    assert ahead[4].tolist() == [0.0, 0.0]  # a user who never walked stays where it is
    assert heard.tolist() == [True, True, True, True, True, False]  # 6 s of silence: not guessed at
    # the walker's phone goes on reporting scans without steps until 12 s: it stands; heard until 12 s
    columns.update([walker], [12_000], trails)
    ahead, _, heard = columns.extrapolated(np.array([0, 0]), np.array([11_000, 13_000]))
    assert ahead.tolist() == [[0.0, 0.0], [0.0, 0.0]]
    assert heard.tolist() == [True, True]


def test_the_columns_bound_the_walk_after_a_time_by_the_latest_batch() -> None:
    """``reach``: 0 for a time the user has not reported past, the latest batch's walk for a time inside
    it (at least the walk since), infinity for an older time; a user new since has walked since its start."""
    trails = Trails()
    track = _east(trails, 0, 1.4)  # ten seconds, 1.4 m a second
    columns = SlotColumns()
    columns.reset(0)
    columns.update([track], [10_000], trails)
    assert columns.reach(np.array([0, 0]), np.array([10_000, 3_000])).tolist() == pytest.approx([0.0, 14.0])
    columns.begin([track])
    track.lay(trails, [10_500, 11_000], [0.7, 0.7], [0.0, 0.0], [0.7, 0.7], (1.4, 0.0), (1.4, 0.0), math.nan)
    track.last_t_ms = 11_000
    columns.update([track], [11_000], trails)
    reach = columns.reach(np.zeros(3, np.int64), np.array([10_200, 9_000, 11_000]))
    assert reach.tolist() == pytest.approx([1.4, math.inf, 0.0])
    _, walked, _ = carried_since(trails, np.zeros(1, np.int64), np.array([11_000]), np.array([10_200]))
    assert walked[0] <= reach[0]
