"""Motion update (DynamicSLAM Eq. 4-8), batched over users: ``prange`` over users, a plain loop over
their steps and particles."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from slam_core.filter.floor_plan import PlanArrays
from slam_core.filter.kernels.arrays import (
    BIAS,
    CTRL_COV,
    HEADING,
    LAST_OBS_HEADING,
    LOGW,
    RNG_CTR,
    RNG_KEY,
    SCALE,
    WALK,
    FilterArrays,
    X,
    Y,
)
from slam_core.filter.kernels.linalg2 import wrap_angle
from slam_core.filter.kernels.rng import normal, normal_at
from slam_core.filter.kernels.serial import serial_twin
from slam_core.filter.kernels.walls import (
    MAX_NEAR_WALLS,
    all_free,
    crosses_wall,
    mark_crossings,
    near_walls,
    walkable,
    wholly_walkable,
)
from slam_core.filter.kernels.weights import normalise_log_weights_ess

MODEL_PAPER = 0
MODEL_BIAS_SCALE = 1


@njit(cache=True, nogil=True)
def _advance_user(
    arrays: FilterArrays,
    u: int,
    first: int,
    stop: int,
    step_length: np.ndarray,
    step_heading: np.ndarray,
    motion: tuple[int, float, float, float, float],
    plan: PlanArrays,
    plan_weights: tuple[bool, float, float, float],
) -> bool:
    x, y, heading = arrays[X], arrays[Y], arrays[HEADING]
    logw = arrays[LOGW]
    use_plan, log_crossing, log_outside, ess_threshold = plan_weights
    grid = (plan[0], plan[1], plan[2], plan[3], plan[4])
    cell_start, cell_walls, walls = plan[5], plan[6], plan[7]
    raster_frame, raster, free, blocked_sum = (plan[8], plan[9], plan[10]), plan[11], plan[12], plan[13]
    penalised = False
    # the plan's scratch in one allocation (one per array cost as much as the tests of a user in the open):
    # the steps' starts, whether each crossed a wall, and the walls near the user
    n_scratch = x.shape[1] if use_plan else 0
    scratch = np.empty(3 * n_scratch + 4 * MAX_NEAR_WALLS)
    x_before, y_before, hit = (
        scratch[:n_scratch],
        scratch[n_scratch : 2 * n_scratch],
        scratch[2 * n_scratch : 3 * n_scratch],
    )
    near = scratch[3 * n_scratch :].reshape((MAX_NEAR_WALLS, 4))
    bias, scale, walk = arrays[BIAS], arrays[SCALE], arrays[WALK]
    ctrl_cov, last_obs_heading = arrays[CTRL_COV], arrays[LAST_OBS_HEADING]
    rng_key, rng_ctr = arrays[RNG_KEY], arrays[RNG_CTR]
    model, sigma_l, sigma_phi, sigma_walk, ctrl_cov_cap = motion
    n_particles = x.shape[1]
    key = rng_key[u]
    counter = rng_ctr[u]
    one = np.uint64(1)
    for s in range(first, stop):
        length = step_length[s]
        obs = step_heading[s]
        previous = last_obs_heading[u]
        d_obs = 0.0 if math.isnan(previous) else wrap_angle(obs - previous)
        low_x = low_y = math.inf
        high_x = high_y = -math.inf
        for m in range(n_particles):
            n_len = normal_at(key, counter)
            n_h = normal_at(key, counter + one)
            counter += np.uint64(2)
            if model == MODEL_PAPER:
                # Eq. 5: L ~ N(l, sigma_l), phi ~ N(phi_hat, sigma_phi); Eq. 6: heading += phi
                step = length + sigma_l * n_len
                h = heading[u, m] + d_obs + sigma_phi * n_h
            else:
                # Beyond the paper: phone heading + per-particle bias + slow walk, scaled length. The white
                # per-step heading noise of Eq. 5 is left out here: it moves a particle l sigma_phi ~ 2 cm
                # sideways per step and averages out, while a third normal per particle cost a third of
                # the update.
                walk[u, m] += sigma_walk * n_h
                step = scale[u, m] * length + sigma_l * n_len
                h = obs + bias[u, m] + walk[u, m]
            h = wrap_angle(h)
            heading[u, m] = h
            x0, y0 = x[u, m], y[u, m]
            x1, y1 = x0 + step * math.cos(h), y0 + step * math.sin(h)
            x[u, m] = x1  # Eq. 7
            y[u, m] = y1  # Eq. 8
            if use_plan:
                x_before[m], y_before[m] = x0, y0
                low_x, high_x = min(low_x, x0, x1), max(high_x, x0, x1)
                low_y, high_y = min(low_y, y0, y1), max(high_y, y0, y1)
        # beyond the paper: the floor plan's likelihood of each particle's step, unless every step stayed
        # in cells without walls, wholly walkable. Otherwise the steps are tested against the few walls near
        # the user, and their ends against the raster only where the user's box is not wholly walkable.
        if use_plan and not all_free(grid, free, low_x, low_y, high_x, high_y):
            n_near = near_walls(grid, cell_start, cell_walls, walls, low_x, low_y, high_x, high_y, near)
            if n_near > 0:
                mark_crossings(near, n_near, x_before, y_before, x[u], y[u], hit)
            elif n_near < 0:  # more walls than the list holds: each step through the grid
                for m in range(n_particles):
                    crossed = crosses_wall(
                        grid, cell_start, cell_walls, walls, x_before[m], y_before[m], x[u, m], y[u, m]
                    )
                    hit[m] = 1.0 if crossed else 0.0
            test_area = not wholly_walkable(raster_frame, raster, blocked_sum, low_x, low_y, high_x, high_y)
            if n_near != 0 or test_area:
                for m in range(n_particles):
                    if n_near != 0 and hit[m] != 0.0:
                        logw[u, m] += log_crossing
                        penalised = True
                    if test_area and not walkable(raster_frame, raster, x[u, m], y[u, m]):
                        logw[u, m] += log_outside
                        penalised = True
        last_obs_heading[u] = obs
        # P_t: covariance of the control data since the last correction (along/across the step).
        c = math.cos(obs)
        sn = math.sin(obs)
        var_along = sigma_l * sigma_l
        var_across = (length * sigma_phi) ** 2
        ctrl_cov[u, 0] = min(ctrl_cov[u, 0] + var_along * c * c + var_across * sn * sn, ctrl_cov_cap)
        ctrl_cov[u, 1] = ctrl_cov[u, 1] + (var_along - var_across) * c * sn
        ctrl_cov[u, 2] = min(ctrl_cov[u, 2] + var_along * sn * sn + var_across * c * c, ctrl_cov_cap)
        # keep the capped covariance positive definite
        lim = 0.999 * math.sqrt(ctrl_cov[u, 0] * ctrl_cov[u, 2])
        ctrl_cov[u, 1] = max(-lim, min(lim, ctrl_cov[u, 1]))
    rng_ctr[u] = counter
    if not penalised:
        return False
    ess = normalise_log_weights_ess(logw, u)  # the penalties are finite: the row always normalises
    # whether the resampling may act, judged here: most penalised users keep enough effective particles, and
    # a kernel call each only to find that out cost more than the plan's tests. The margin covers rounding:
    # the resampling decides with its own sum.
    return ess_threshold >= 1.0 or ess < ess_threshold * n_particles * (1.0 + 1e-9)


@njit(cache=True, nogil=True, parallel=True)
def motion_update(
    arrays: FilterArrays,
    users: np.ndarray,
    offsets: np.ndarray,
    step_length: np.ndarray,
    step_heading: np.ndarray,
    motion: tuple[int, float, float, float, float],
    plan: PlanArrays,
    plan_weights: tuple[bool, float, float, float],
    resample: np.ndarray,
) -> None:
    """Advance ``users[i]`` by its steps ``offsets[i]:offsets[i+1]`` (lengths in metres, observed headings in
    rad counter-clockwise from east). Users must be distinct within one call. ``motion`` is the model's
    code and parameters: (model, sigma_l, sigma_phi, sigma_walk, control covariance cap). With
    ``plan_weights`` = (True, log-likelihood of crossing a wall, of ending outside the walkable area, the
    resampling's ESS threshold), each particle's step is weighted by the floor plan
    (``slam_core.filter.kernels.walls``) and, where a step was penalised, the user's weights normalised and
    ``resample[i]`` set if the resampling may act on them (``resample_users`` decides); with False the plan is
    not read.

    Per particle and step, two normals are drawn in this order: length noise, then heading noise (paper
    model) or the heading walk's increment (bias-scale model); ``slam_core.filter.reference`` draws them
    identically. The ``prange`` body only calls a plain ``@njit`` function: numba's parfor pass slowed the
    inlined loops 2.5x.
    """
    for i in prange(users.shape[0]):
        resample[i] = _advance_user(
            arrays,
            users[i],
            offsets[i],
            offsets[i + 1],
            step_length,
            step_heading,
            motion,
            plan,
            plan_weights,
        )


@njit(cache=True, nogil=True)
def initialise_user(
    arrays: FilterArrays,
    u: int,
    x0: float,
    y0: float,
    position_sigma: float,
    heading0: float,
    heading_sigma: float,
    bias_sigma: float,
    scale_sigma: float,
) -> None:
    """Particles of a new user around its start fix; bias and scale drawn from their priors."""
    x, y, heading = arrays[X], arrays[Y], arrays[HEADING]
    bias, scale, walk, logw = arrays[BIAS], arrays[SCALE], arrays[WALK], arrays[LOGW]
    rng_key, rng_ctr = arrays[RNG_KEY], arrays[RNG_CTR]
    n_particles = x.shape[1]
    key = rng_key[u]
    for m in range(n_particles):
        x[u, m] = x0 + position_sigma * normal(key, rng_ctr, u)
        y[u, m] = y0 + position_sigma * normal(key, rng_ctr, u)
        heading[u, m] = wrap_angle(heading0 + heading_sigma * normal(key, rng_ctr, u))
        bias[u, m] = bias_sigma * normal(key, rng_ctr, u)
        scale[u, m] = max(0.2, 1.0 + scale_sigma * normal(key, rng_ctr, u))
        walk[u, m] = 0.0
        logw[u, m] = -math.log(n_particles)


motion_update_serial = serial_twin(motion_update)
