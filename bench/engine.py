"""Engine benchmark: motion update, a realistic tick, one human-anchor update, and the speed-up over the
plain-NumPy textbook FastSLAM on identical inputs.

    python bench/engine.py [--users 10000] [--json OUT]

Prints one JSON object: motion_ms; motion_on_floor_ms and motion_plan_ms (the same users on a mall floor,
without and with its plan of walls and walkable area, ``--plan-floor``) and plan_overhead; the same for
users walking the floor's surveyed walks (motion_walks_ms, motion_walks_plan_ms, walks_plan_overhead,
walks_resampled_share); step_ms,
human_anchor_us, reference_ratio (the engine's kernels in parallel, as over a whole building) and
reference_ratio_serial (as the engine runs a call of 100 users by default: serially,
``slam_core.filter.kernels.serial``), and what they were measured on.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from server.slam.numba_cache import configure_numba_cache

configure_numba_cache()
from report import emit

from server.datasets.msindoor import FloorInfo
from slam_core.filter import reference
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.filter.floor_plan import PlanIndex
from slam_core.filter.kernels.serial import PARALLEL_MIN_USERS
from slam_core.filter.params import FilterParams


def _engine(
    n_users: int, params: FilterParams, seed: int = 0, parallel_min_users: int = PARALLEL_MIN_USERS
) -> tuple[DynamicSlam, np.ndarray]:
    engine = DynamicSlam(params, seed=seed, initial_capacity=n_users, parallel_min_users=parallel_min_users)
    rng = np.random.default_rng(seed)
    users = np.array([engine.add_user(*rng.uniform(0, 60, 2)) for _ in range(n_users)])
    # Fault in the maps' fresh zero pages now: the first write to each page of a new engine costs ~10 ms per
    # 100 users, a start-up cost that a long-lived server pays once and that is no part of a tick.
    for name in ("map_mu", "map_cov", "map_type", "map_count", "map_known"):
        getattr(engine.state, name).fill(0)
    return engine, users


def _median_ms(fn, repeats: int) -> float:  # type: ignore[no-untyped-def]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def bench_motion(engine: DynamicSlam, users: np.ndarray, rng: np.random.Generator) -> float:
    offsets = np.arange(users.size + 1)

    def tick() -> None:
        engine.step(
            users, offsets, 0.7 + 0.05 * rng.standard_normal(users.size), rng.uniform(-3, 3, users.size)
        )

    tick()  # warm
    return _median_ms(tick, 7)


def _mall_floor(floor: Path) -> tuple[FloorInfo, PlanIndex]:
    """A floor of the Indoor Location 2.0 data set and the engine's index of its plan."""
    from server.datasets.msindoor import read_floor, read_floor_plan
    from server.ingestion.floor_plans import engine_plan

    info = read_floor(floor)
    wire = read_floor_plan(info).plan
    if wire is None:
        raise SystemExit(f"{floor} has no geojson_map.json")
    return info, engine_plan(wire)


def bench_motion_plan(n_users: int, params: FilterParams, plan: PlanIndex) -> tuple[float, float]:
    """The motion update of users spread over a mall floor's walkable area, without and with its plan (the
    plan's update also resamples the users whose weights the walls spread): medians of alternating runs."""
    rng = np.random.default_rng(1)
    cells = np.argwhere(plan.raster == 1)
    engine = DynamicSlam(params, seed=1, initial_capacity=n_users)
    starts = (cells[rng.integers(0, len(cells), n_users)][:, ::-1] + 0.5) * plan.raster_m
    users = np.array([engine.add_user(*(xy + plan.raster_origin)) for xy in starts])
    offsets = np.arange(users.size + 1)
    plain, planned = [], []
    for k in range(16):
        lengths = 0.7 + 0.05 * rng.standard_normal(users.size)
        headings = rng.uniform(-3, 3, users.size)
        engine.set_floor_plan(0, plan if k % 2 else None)
        t0 = time.perf_counter()
        engine.step(users, offsets, lengths, headings)
        (planned if k % 2 else plain).append((time.perf_counter() - t0) * 1e3)
    return statistics.median(plain[1:]), statistics.median(planned[1:])


STEP_M = 0.7
"""A stride along the surveyed walks."""


def _walked_steps(waypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A surveyed walk (its waypoints' x, y) as strides out and back: the start of each, its length, its
    heading (rad, counter-clockwise from east), a closed loop that a user can walk round and round."""
    xy = waypoints[:, 1:3]
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    at = np.arange(0.0, along[-1], STEP_M)
    points = np.column_stack([np.interp(at, along, xy[:, 0]), np.interp(at, along, xy[:, 1])])
    points = np.concatenate([points, points[-2:0:-1]])  # back the way it came
    moves = np.diff(np.concatenate([points, points[:1]]), axis=0)
    return points, np.hypot(moves[:, 0], moves[:, 1]), np.arctan2(moves[:, 1], moves[:, 0])


def bench_motion_plan_walks(
    n_users: int, params: FilterParams, info: FloorInfo, plan: PlanIndex
) -> tuple[float, float, float]:
    """The motion update of users walking the floor's surveyed walks (each user one walk, from a random point
    of it, out and back), with each phone's dead-reckoning error as measured on these walks (a heading bias
    of sigma 12 deg and a stride scale of sigma 0.14 a phone), without and with the floor's plan: medians of
    alternating runs, and the share of users a step with the plan resampled (walls spread their weights)."""
    from server.datasets.msindoor import read_trace

    walks = [_walked_steps(w) for w in (read_trace(p).waypoints for p in info.traces) if len(w) >= 2]
    walks = [w for w in walks if len(w[1]) >= 2]
    rng = np.random.default_rng(1)
    engine = DynamicSlam(params, seed=1, initial_capacity=n_users)
    walk_of = np.arange(n_users) % len(walks)
    at = np.array([rng.integers(0, len(walks[w][1])) for w in walk_of])
    users = np.array([engine.add_user(*walks[w][0][k]) for w, k in zip(walk_of, at, strict=True)])
    bias = rng.normal(0.0, np.radians(12.0), n_users)
    scale = np.clip(rng.normal(1.0, 0.14, n_users), 0.5, 1.5)
    offsets = np.arange(users.size + 1)
    plain, planned, touched = [], [], []
    for k in range(24):
        index = [(a + k) % len(walks[w][1]) for w, a in zip(walk_of, at, strict=True)]
        lengths = scale * np.array([walks[w][1][i] for w, i in zip(walk_of, index, strict=True)])
        headings = bias + np.array([walks[w][2][i] for w, i in zip(walk_of, index, strict=True)])
        engine.set_floor_plan(0, plan if k % 2 else None)
        before = engine.state.n_resamples[users].copy() if k % 2 else None
        t0 = time.perf_counter()
        engine.step(users, offsets, lengths, headings)
        (planned if k % 2 else plain).append((time.perf_counter() - t0) * 1e3)
        if before is not None:
            touched.append(float(np.mean(engine.state.n_resamples[users] != before)))
    return statistics.median(plain[1:]), statistics.median(planned[1:]), float(np.mean(touched))


def bench_tick(engine: DynamicSlam, users: np.ndarray, rng: np.random.Generator) -> float:
    """All users step; 5 % detect a building anchor; 2 % are in an encounter; every estimate is read."""
    offsets = np.arange(users.size + 1)

    def tick() -> None:
        engine.step(
            users, offsets, 0.7 + 0.05 * rng.standard_normal(users.size), rng.uniform(-3, 3, users.size)
        )
        seen = rng.choice(users, size=max(1, users.size // 20), replace=False)
        engine.observe_building_anchors(seen, rng.integers(0, 5, seen.size))
        pair = rng.choice(users, size=2 * max(1, users.size // 100), replace=False).reshape(2, -1)
        engine.observe_encounters(
            pair[0], pair[1], rng.uniform(0.5, 4.0, pair.shape[1]), np.full(pair.shape[1], 4.0)
        )
        engine.summaries(users)

    tick()
    return _median_ms(tick, 7)


def bench_human_anchor(params: FilterParams) -> float:
    engine, users = _engine(2, params)
    u = users[:1]
    peer_mean = np.array([[3.0, 4.0]])
    peer_cov = np.array([[1.0, 0.1, 1.2]])
    z = np.array([4.0])
    r = np.array([4.0])
    engine._human_update(u, peer_mean, peer_cov, z, r)  # warm
    n = 2000
    t0 = time.perf_counter()
    for _ in range(n):
        engine._human_update(u, peer_mean, peer_cov, z, r)
    return (time.perf_counter() - t0) / n * 1e6


REFERENCE_USERS = 100


def bench_reference_ratio(
    params: FilterParams,
    n_users: int = REFERENCE_USERS,
    n_ticks: int = 5,
    repeats: int = 7,
    parallel_min_users: int = PARALLEL_MIN_USERS,
) -> tuple[float, float, float]:
    """Same users, same inputs, same random streams: textbook objects vs compiled kernels. The engine's
    time is the median of ``repeats`` runs from the same start (one run of a few milliseconds is at the
    mercy of the scheduler); the reference, which takes seconds, runs once."""
    rng = np.random.default_rng(1)
    lengths = 0.7 + 0.05 * rng.standard_normal((n_ticks, n_users))
    headings = rng.uniform(-3, 3, (n_ticks, n_users))
    detected = rng.integers(0, 5, (n_ticks, n_users))
    offsets = np.arange(n_users + 1)

    def run_engine() -> float:
        engine, users = _engine(n_users, params, seed=3, parallel_min_users=parallel_min_users)
        t0 = time.perf_counter()
        for k in range(n_ticks):
            engine.step(users, offsets, lengths[k], headings[k])
            engine.observe_building_anchors(users, detected[k])
            engine.summaries(users)
        return time.perf_counter() - t0

    t_engine = statistics.median(run_engine() for _ in range(repeats))
    engine, users = _engine(n_users, params, seed=3)
    refs = [reference.from_state(engine.state, int(u)) for u in users]
    t0 = time.perf_counter()
    for k in range(n_ticks):
        for i, ref in enumerate(refs):
            reference.motion(ref, float(lengths[k, i]), float(headings[k, i]), params)
            reference.building_anchor(ref, int(detected[k, i]), params)
            reference.resample(ref, params)
            reference.summary(ref)
    t_ref = time.perf_counter() - t0
    return t_ref / t_engine, t_ref * 1e3, t_engine * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--users", type=int, default=10_000)
    parser.add_argument("--json", type=Path, metavar="OUT")
    parser.add_argument(
        "--plan-floor",
        type=Path,
        default=Path(__file__).resolve().parents[1] / "crowdslam-data/datasets/msindoor20/site1/F1",
        help="a floor of the Indoor Location 2.0 data set whose plan the motion update is timed with "
        "(crowdslam datasets fetch msindoor20 puts it there)",
    )
    args = parser.parse_args()
    params = FilterParams()
    rng = np.random.default_rng(0)
    engine, users = _engine(args.users, params)
    motion_ms = bench_motion(engine, users, rng)
    floor_info, floor_plan = _mall_floor(args.plan_floor)
    plain_ms, plan_ms = bench_motion_plan(args.users, params, floor_plan)
    walks_plain_ms, walks_plan_ms, walks_resampled = bench_motion_plan_walks(
        args.users, params, floor_info, floor_plan
    )
    step_ms = bench_tick(engine, users, rng)
    human_us = bench_human_anchor(params)
    # warm the small-input path of every kernel before timing it against the reference
    bench_reference_ratio(params, n_users=2, n_ticks=1, repeats=1)
    # the 100 users in parallel, as a call over a whole building runs; and as the engine dispatches a call
    # of 100 users by default: serially (slam_core.filter.kernels.serial), steadier on a busy machine
    ratio, ref_ms, eng_ms = bench_reference_ratio(params, parallel_min_users=1)
    ratio_serial, _, eng_serial_ms = bench_reference_ratio(params)
    import numba

    result = {
        "users": args.users,
        "particles": params.n_particles,
        "threads": numba.get_num_threads(),
        "motion_ms": round(motion_ms, 3),
        "motion_on_floor_ms": round(plain_ms, 3),
        "motion_plan_ms": round(plan_ms, 3),
        "plan_overhead": round(plan_ms / plain_ms, 2),
        "motion_walks_ms": round(walks_plain_ms, 3),
        "motion_walks_plan_ms": round(walks_plan_ms, 3),
        "walks_plan_overhead": round(walks_plan_ms / walks_plain_ms, 2),
        "walks_resampled_share": round(walks_resampled, 3),
        "plan_floor": "/".join(args.plan_floor.parts[-2:]),
        "step_ms": round(step_ms, 3),
        "human_anchor_us": round(human_us, 2),
        "reference_ratio": round(ratio, 1),
        "reference_ratio_serial": round(ratio_serial, 1),
        "reference_ms": round(ref_ms, 1),
        "engine_ms_same_inputs": round(eng_ms, 3),
        "engine_serial_ms_same_inputs": round(eng_serial_ms, 3),
        "reference_users": REFERENCE_USERS,
    }
    emit(result, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
