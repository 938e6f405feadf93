"""The floor plan in the motion update: its index and raster against brute force, the kernel against the
NumPy reference, the filter's invariants, and what a plan does to a drifting walker."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from matplotlib.path import Path as PolygonPath

from slam_core.filter import reference
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.filter.floor_plan import PlanIndex, dominant_axis
from slam_core.filter.kernels.walls import (
    MAX_NEAR_WALLS,
    crosses_wall,
    mark_crossings,
    near_walls,
    walkable,
    wholly_walkable,
)
from slam_core.filter.params import FilterParams, FloorPlanParams, ResamplingParams
from tests.slam_core.filter.helpers import assert_matches, to_reference

SQUARE = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 30.0], [0.0, 30.0]])
HOLE = np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]])


def _random_walls(rng: np.random.Generator, n: int) -> np.ndarray:
    start = rng.uniform(0, 40, size=(n, 2))
    angle = rng.uniform(0, 2 * math.pi, n)
    length = rng.exponential(4.0, n)
    return np.column_stack([start, start + length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])])


def test_the_grid_finds_every_crossing_brute_force_finds() -> None:
    rng = np.random.default_rng(1)
    walls = _random_walls(rng, 300)
    plan = PlanIndex.build(walls, cell_m=2.0)
    arrays = plan.arrays()
    crossings = 0
    for _ in range(3000):
        p0 = rng.uniform(-2, 42, 2)
        p1 = p0 + rng.normal(0, 1.0, 2)
        expected = reference.crosses_any_wall(walls, *p0, *p1)
        assert crosses_wall(arrays[:5], *arrays[5:8], *p0, *p1) == expected, (p0, p1)
        crossings += expected
    assert 300 < crossings < 2700  # both answers were exercised


def _segment_meets_box(wall: np.ndarray, low: np.ndarray, high: np.ndarray) -> bool:
    """Brute force: whether the segment has a point in the box (Liang-Barsky clipping)."""
    start, delta = wall[:2], wall[2:] - wall[:2]
    t0, t1 = 0.0, 1.0
    for k in range(2):
        if delta[k] == 0.0:
            if not low[k] <= start[k] <= high[k]:
                return False
            continue
        a, b = (low[k] - start[k]) / delta[k], (high[k] - start[k]) / delta[k]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    return t0 <= t1


def test_a_shared_edge_drawn_twice_is_one_wall() -> None:
    """Two shops side by side draw their shared edge twice, once each way round: the plan keeps it once, and
    every step crosses the plan as it crossed the walls as drawn."""
    rng = np.random.default_rng(14)
    walls = _random_walls(rng, 100)
    drawn = np.vstack([walls, walls[:40, [2, 3, 0, 1]], walls[40:60]])
    plan = PlanIndex.build(drawn, cell_m=2.0)
    np.testing.assert_array_equal(plan.walls, walls)
    assert (plan.axis_rad, plan.axis_strength) == dominant_axis(drawn)  # the grid is read from the drawing
    arrays = plan.arrays()
    for _ in range(500):
        p0 = rng.uniform(-2, 42, 2)
        p1 = p0 + rng.normal(0, 2.0, 2)
        assert crosses_wall(arrays[:5], *arrays[5:8], *p0, *p1) == reference.crosses_any_wall(drawn, *p0, *p1)


def test_the_walls_near_a_box_are_each_wall_that_meets_it_once() -> None:
    """The short list a user's steps are tested against holds every wall with a point in the user's box,
    once, and no wall whose own box misses it; a list too short for them says so (-1)."""
    rng = np.random.default_rng(11)
    walls = _random_walls(rng, 300)
    plan = PlanIndex.build(walls, cell_m=2.0)
    arrays = plan.arrays()
    near = np.empty((MAX_NEAR_WALLS, 4))
    listed_total = 0
    for _ in range(500):
        low = rng.uniform(-2, 40, 2)
        high = low + rng.uniform(0, 6, 2)
        n = near_walls(arrays[:5], *arrays[5:8], *low, *high, near)
        assert n >= 0
        got = {tuple(w) for w in near[:n]}
        assert len(got) == n  # each wall once
        meets = {tuple(w) for w in walls if _segment_meets_box(w, low, high)}
        assert meets <= got
        boxes_meet = {
            tuple(w)
            for w in walls
            if min(w[0], w[2]) <= high[0] and max(w[0], w[2]) >= low[0]
            if min(w[1], w[3]) <= high[1] and max(w[1], w[3]) >= low[1]
        }
        assert got <= boxes_meet
        listed_total += n
    assert listed_total > 500  # boxes met walls
    short = np.empty((2, 4))
    assert near_walls(arrays[:5], *arrays[5:8], 0.0, 0.0, 40.0, 40.0, short) == -1


def test_a_users_steps_cross_the_walls_near_it_as_the_grid_says() -> None:
    """``mark_crossings`` over ``near_walls`` gives, step by step, the grid's answer (the kernel's fast path
    against its general one)."""
    rng = np.random.default_rng(12)
    walls = _random_walls(rng, 300)
    plan = PlanIndex.build(walls, cell_m=2.0)
    arrays = plan.arrays()
    near = np.empty((MAX_NEAR_WALLS, 4))
    crossings = 0
    for _ in range(300):
        centre = rng.uniform(0, 40, 2)
        x0, y0 = (centre + rng.normal(0, 1.0, (75, 2))).T
        heading = rng.uniform(-math.pi, math.pi)
        step = rng.uniform(0.3, 1.0, 75)
        x1, y1 = x0 + step * math.cos(heading), y0 + step * math.sin(heading)
        low = (min(x0.min(), x1.min()), min(y0.min(), y1.min()))
        high = (max(x0.max(), x1.max()), max(y0.max(), y1.max()))
        n = near_walls(arrays[:5], *arrays[5:8], *low, *high, near)
        if n < 0:
            continue
        hit = np.full(75, 7.0)  # whatever the scratch held before
        mark_crossings(near, n, x0, y0, x1, y1, hit)
        expected = [crosses_wall(arrays[:5], *arrays[5:8], *a) for a in zip(x0, y0, x1, y1, strict=True)]
        np.testing.assert_array_equal(hit, np.array(expected, dtype=float))
        crossings += int(hit.sum())
    assert crossings > 100


def test_a_wholly_walkable_box_holds_only_walkable_cells() -> None:
    plan = PlanIndex.build(np.zeros((0, 4)), [SQUARE, HOLE], raster_m=0.5)
    arrays = plan.arrays()
    rng = np.random.default_rng(13)
    answers = set()
    for _ in range(2000):
        low = rng.uniform(-3, 42, 2)
        high = low + rng.uniform(0, 5, 2)
        got = wholly_walkable(arrays[8:11], arrays[11], arrays[13], *low, *high)
        c0, r0 = np.floor((low - plan.raster_origin) / plan.raster_m).astype(int)
        c1, r1 = np.floor((high - plan.raster_origin) / plan.raster_m).astype(int)
        rows, columns = plan.raster.shape
        inside = c0 >= 0 and r0 >= 0 and c1 < columns and r1 < rows
        assert got == (inside and bool(np.all(plan.raster[r0 : r1 + 1, c0 : c1 + 1] == 1)))
        answers.add(got)
    assert answers == {True, False}
    empty = PlanIndex.empty().arrays()
    assert wholly_walkable(empty[8:11], empty[11], empty[13], -1e6, -1e6, 1e6, 1e6)


def test_the_raster_is_the_even_odd_inside_of_the_rings() -> None:
    plan = PlanIndex.build(np.zeros((0, 4)), [SQUARE, HOLE], raster_m=0.25)
    rng = np.random.default_rng(2)
    points = rng.uniform(-5, 45, size=(5000, 2))
    expected = PolygonPath(SQUARE).contains_points(points) & ~PolygonPath(HOLE).contains_points(points)
    got = plan.walkable(points)
    # the raster answers for its cell's centre: only points within a cell of an edge may differ
    near_edge = np.zeros(len(points), dtype=bool)
    for ring in (SQUARE, HOLE):
        for a, b in zip(ring, np.roll(ring, -1, axis=0), strict=True):
            t = np.clip(((points - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
            near_edge |= np.linalg.norm(points - (a + t[:, None] * (b - a)), axis=1) < 0.25 * math.sqrt(2)
    assert np.array_equal(got[~near_edge], expected[~near_edge])
    arrays = plan.arrays()
    assert all(
        walkable(arrays[8:11], arrays[11], *p) == g for p, g in zip(points[:500], got[:500], strict=True)
    )
    assert PlanIndex.empty().walkable(points).all()


def test_free_cells_hold_no_wall_and_only_walkable_ground() -> None:
    """A free cell of the wall grid (the motion update skips users whose steps stay in free cells) holds no
    wall and every point in it is walkable; a corridor of free cells runs between the walls."""
    walls = np.array([[0.0, 0.0, 40.0, 0.0], [0.0, 10.0, 40.0, 10.0]])
    plan = PlanIndex.build(walls, [SQUARE, HOLE], cell_m=2.0, raster_m=0.25)
    rng = np.random.default_rng(5)
    columns = plan.grid_shape[1]
    free = np.flatnonzero(plan.free)
    assert free.size > 20
    for cell in free:
        assert plan.cell_start[cell] == plan.cell_start[cell + 1]
        r, c = divmod(int(cell), columns)
        corner = np.array(plan.origin) + np.array([c, r]) * plan.cell_m
        assert plan.walkable(corner + rng.uniform(0, plan.cell_m, size=(20, 2))).all()
    # a cell crossed by a wall, or in the hole, is never free
    for point in ([5.0, 0.0], [15.0, 15.0]):
        c, r = ((np.array(point) - plan.origin) // plan.cell_m).astype(int)
        assert plan.free[r * columns + c] == 0


def test_a_huge_site_gets_coarser_cells_not_a_huge_raster() -> None:
    site = np.array([[0.0, 0.0], [20_000.0, 0.0], [20_000.0, 20_000.0], [0.0, 20_000.0]])
    plan = PlanIndex.build(np.array([[0.0, 0.0, 20_000.0, 20_000.0]]), [site])
    assert plan.raster.size <= 4_100_000
    assert plan.cell_start.size <= 4_100_000


def test_invalid_plans_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        PlanIndex.build(np.array([[0.0, 0.0, np.nan, 1.0]]))
    with pytest.raises(ValueError, match="three points"):
        PlanIndex.build(np.zeros((0, 4)), [np.array([[0.0, 0.0], [1.0, 1.0]])])
    diagonals = np.tile([0.0, 0.0, 1000.0, 1000.0], (100, 1))  # each wall's box: 250,000 cells
    diagonals[:, 0] += np.arange(100) * 0.01  # distinct walls (a repeated one is indexed once)
    with pytest.raises(ValueError, match="boxes span"):
        PlanIndex.build(diagonals)
    with pytest.raises(ValueError, match="in \\(0, 1\\]"):
        FloorPlanParams(wall_crossing_likelihood=0.0)


def _corridor() -> PlanIndex:
    """A corridor 3 m wide along x from 0 to 60 m, walls on both sides, between two large rooms' walls."""
    walls = np.array(
        [[0.0, 0.0, 60.0, 0.0], [0.0, 3.0, 60.0, 3.0], [0.0, 0.0, 0.0, 3.0], [60.0, 0.0, 60.0, 3.0]]
    )
    outline = np.array([[-1.0, -1.0], [61.0, -1.0], [61.0, 4.0], [-1.0, 4.0]])
    return PlanIndex.build(walls, [outline])


def test_the_kernel_weighs_steps_as_the_reference_does() -> None:
    params = FilterParams(n_particles=16, resampling=ResamplingParams(ess_threshold=1e-9))
    engine = DynamicSlam(params, seed=5)
    plan = _corridor()
    engine.set_floor_plan(0, plan)
    u = engine.add_user(2.0, 1.5, heading=0.0, position_sigma=0.8)
    ref = to_reference(engine, u)
    for _ in range(20):
        engine.step(np.array([u]), np.array([0, 1]), np.array([0.7]), np.array([0.15]))
        reference.motion(ref, 0.7, 0.15, params, plan)
    assert_matches(engine, u, ref)
    w = np.exp(engine.state.logw[u])
    assert np.isclose(w.sum(), 1.0)
    assert w.max() > 5 * w.min()  # the walls told particles apart


def test_users_the_walls_thin_out_are_resampled_as_the_reference_does() -> None:
    """With the default resampling, a user is resampled after a step exactly when the walls left it too few
    effective particles (the kernel judges it; the reference resamples by its own test)."""
    params = FilterParams(n_particles=32)
    engine = DynamicSlam(params, seed=6)
    plan = _corridor()
    engine.set_floor_plan(0, plan)
    u = engine.add_user(2.0, 1.5, heading=0.0, position_sigma=0.8)
    ref = to_reference(engine, u)
    resampled = 0
    for k in range(40):
        heading = 0.15 if k % 10 < 5 else -0.15  # zig-zag into both walls
        engine.step(np.array([u]), np.array([0, 1]), np.array([0.7]), np.array([heading]))
        reference.motion(ref, 0.7, heading, params, plan)
        resampled += reference.resample(ref, params)
    assert_matches(engine, u, ref)
    assert 0 < resampled < 40
    assert engine.state.n_resamples[u] == resampled


def _drift(plan: PlanIndex | None, seed: int) -> np.ndarray:
    """A walker going east along the corridor's middle while its phone's heading reads 8 degrees left."""
    engine = DynamicSlam(FilterParams(), seed=seed)
    engine.set_floor_plan(0, plan)
    u = engine.add_user(1.0, 1.5, heading=0.0, position_sigma=0.3)
    track = []
    for _ in range(70):
        engine.step(np.array([u]), np.array([0, 1]), np.array([0.7]), np.array([math.radians(8.0)]))
        state = engine.state
        assert np.all(np.isfinite(state.x[u]))
        assert np.all(np.isfinite(state.logw[u]))
        assert np.isclose(np.exp(state.logw[u]).sum(), 1.0)
        track.append(engine.means(np.array([u]))[0])
    return np.array(track)


def test_a_plan_keeps_a_drifting_walker_in_its_corridor() -> None:
    for seed in range(3):
        free = _drift(None, seed)
        held = _drift(_corridor(), seed)
        assert free[-1, 1] > 6.0  # 49 m at 8 degrees: ~7 m north of the corridor's middle
        assert 0.0 < held[-1, 1] < 3.0, held[-1]
        assert held[-1, 0] > 35.0  # it still walked east


def test_a_user_admitted_under_a_plan_draws_its_step_scale_from_the_plans_prior() -> None:
    """The walls bias a walk's scale, so a plan brings its own, narrower scale prior; without one the motion
    model's stays (the anchors learn the scale there)."""
    params = FilterParams(floor_plan=FloorPlanParams(step_scale_sigma=0.0))
    with_plan, without = DynamicSlam(params, seed=3), DynamicSlam(params, seed=3)
    with_plan.set_floor_plan(0, _corridor())
    empty = DynamicSlam(params, seed=3)
    empty.set_floor_plan(0, PlanIndex.empty())
    held = with_plan.add_user(2.0, 1.5)
    assert np.all(with_plan.state.scale[held] == 1.0)
    for engine in (without, empty):
        spread = float(np.std(engine.state.scale[engine.add_user(2.0, 1.5)]))
        assert 0.08 < spread < 0.16  # MotionParams.step_scale_sigma, 0.12
    default = DynamicSlam(FilterParams(), seed=3)
    default.set_floor_plan(0, _corridor())
    spread = float(np.std(default.state.scale[default.add_user(2.0, 1.5)]))
    assert 0.03 < spread < 0.07  # FloorPlanParams.step_scale_sigma, 0.05
    with pytest.raises(ValueError, match="step_scale_sigma"):
        FloorPlanParams(step_scale_sigma=-0.01)


def test_without_a_plan_the_update_is_the_plain_motion_update() -> None:
    a, b = DynamicSlam(FilterParams(), seed=2), DynamicSlam(FilterParams(), seed=2)
    b.set_floor_plan(0, PlanIndex.empty())
    ua, ub = a.add_user(0.0, 0.0), b.add_user(0.0, 0.0)
    for engine, u in ((a, ua), (b, ub)):
        engine.step(np.array([u]), np.array([0, 3]), np.array([0.7, 0.7, 0.6]), np.array([0.1, 0.2, 0.1]))
    np.testing.assert_array_equal(a.state.x, b.state.x)
    np.testing.assert_array_equal(a.state.logw, b.state.logw)


def test_the_plan_is_not_pickled_with_the_filter() -> None:
    import pickle

    engine = DynamicSlam(replace(FilterParams(), n_particles=8), seed=1)
    engine.set_floor_plan(0, _corridor())
    restored = pickle.loads(pickle.dumps(engine))
    assert restored.floor_plans == {}


def test_each_floor_s_plan_weighs_the_steps_of_the_users_on_it() -> None:
    """Users on two floors in one step call: each moves as it would alone under its own floor's plan (and a
    floor with no plan moves its users as a building with none does)."""
    params = FilterParams(n_particles=16, resampling=ResamplingParams(ess_threshold=1e-9))
    both = DynamicSlam(params, seed=5)
    both.set_floor_plan(1, _corridor())
    lone_plan, lone_free = DynamicSlam(params, seed=5), DynamicSlam(params, seed=5)
    lone_plan.set_floor_plan(0, _corridor())
    up = both.add_user(2.0, 1.5, position_sigma=0.8, level=1)
    down = both.add_user(2.0, 1.5, position_sigma=0.8, level=0)
    assert both.levels[[up, down]].tolist() == [1, 0]
    a = lone_plan.add_user(2.0, 1.5, position_sigma=0.8)
    lone_free.add_user(0.0, 0.0)  # the second admission draws as the second user of ``both`` does
    b = lone_free.add_user(2.0, 1.5, position_sigma=0.8)
    lengths, headings = np.array([0.7, 0.7, 0.6, 0.7]), np.array([1.5, 1.5, 1.6, 1.5])
    for _ in range(5):
        both.step(np.array([down, up]), np.array([0, 2, 4]), lengths, headings)
        lone_plan.step(np.array([a]), np.array([0, 2]), lengths[2:], headings[2:])
        lone_free.step(np.array([b]), np.array([0, 2]), lengths[:2], headings[:2])
    np.testing.assert_array_equal(both.state.y[up], lone_plan.state.y[a])
    np.testing.assert_array_equal(both.state.logw[up], lone_plan.state.logw[a])
    np.testing.assert_array_equal(both.state.y[down], lone_free.state.y[b])
    np.testing.assert_array_equal(both.state.logw[down], lone_free.state.logw[b])
    assert np.ptp(both.state.logw[up]) > 1.0  # the corridor's walls weigh the walk north down upstairs
    assert np.ptp(both.state.logw[down]) < 1e-9  # and nothing does so downstairs
    # a change of floor: the particles stay, the new floor's plan weighs the next steps
    both.set_levels(np.array([down]), np.array([1]))
    assert both.levels[down] == 1
    with pytest.raises(ValueError, match="unknown user slot"):
        both.set_levels(np.array([99]), np.array([1]))
