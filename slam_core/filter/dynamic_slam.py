"""DynamicSLAM (Algorithm 2) for many users at once: a Python orchestrator over compiled batch kernels.

Inputs are validated before any kernel runs, so a call either applies completely or raises without
touching the state. Randomness comes from per-user counter streams keyed by (seed, admission number).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from slam_core.filter.dense_ids import REPEATED, UNKNOWN, slots_problem, unique_ints
from slam_core.filter.floor_plan import PlanIndex
from slam_core.filter.kernels.building import (
    building_anchor_update,
    building_anchor_update_serial,
    merge_crowd_anchors,
    merge_crowd_anchors_serial,
)
from slam_core.filter.kernels.human import human_anchor_update, human_anchor_update_serial
from slam_core.filter.kernels.motion import (
    MODEL_BIAS_SCALE,
    MODEL_PAPER,
    initialise_user,
    motion_update,
    motion_update_serial,
)
from slam_core.filter.kernels.resampling import SCHEME_CODES, resample_users, resample_users_serial
from slam_core.filter.kernels.serial import PARALLEL_MIN_USERS, pick
from slam_core.filter.kernels.summary import (
    summarise,
    summarise_serial,
    weighted_means,
    weighted_means_serial,
)
from slam_core.filter.params import FilterParams
from slam_core.filter.state import FilterState, SlotAllocator, user_key

SUMMARY_FIELDS = ("x", "y", "cov_xx", "cov_xy", "cov_yy", "best_x", "best_y", "heading")
_NO_PLAN = PlanIndex.empty()


@dataclass(frozen=True)
class CrowdMap:
    """A shared anchor map to seed new users' particle maps (the server keeps it in SQL)."""

    mean: np.ndarray  # (N, 2)
    cov: np.ndarray  # (N, 3) xx, xy, yy
    type: np.ndarray  # (N,) int
    known: np.ndarray  # (N,) bool
    crowd_id: np.ndarray  # (N,) int64

    def __post_init__(self) -> None:
        n = self.mean.shape[0]
        if self.mean.shape != (n, 2) or self.cov.shape != (n, 3):
            raise ValueError("crowd map: mean must be (N, 2) and cov (N, 3)")
        if self.type.shape != (n,) or self.known.shape != (n,) or self.crowd_id.shape != (n,):
            raise ValueError("crowd map: type, known and crowd_id must be (N,)")
        if not (np.all(np.isfinite(self.mean)) and np.all(np.isfinite(self.cov))):
            raise ValueError("crowd map: non-finite mean or covariance")
        if np.any(self.cov[:, 0] <= 0) or np.any(self.cov[:, 0] * self.cov[:, 2] - self.cov[:, 1] ** 2 <= 0):
            raise ValueError("crowd map: covariances must be positive definite")

    @classmethod
    def empty(cls) -> CrowdMap:
        return cls(
            np.zeros((0, 2)),
            np.zeros((0, 3)),
            np.zeros(0, np.int64),
            np.zeros(0, bool),
            np.zeros(0, np.int64),
        )


@dataclass(frozen=True)
class EncounterOutcome:
    applied: np.ndarray  # (E,) bool: passed the gate and was applied to at least one of the two users
    mahalanobis: np.ndarray  # (E,) user-level normalised innovation |z - d| / sqrt(var)


class DynamicSlam:
    """Every user's particle filter in one struct-of-arrays state. Each user is on one floor (``levels``,
    set by the tracker, which keeps the belief over floors: ``slam_core.tracking.floors``); each floor's plan
    weighs the steps of the users on it (beyond the papers)."""

    def __init__(
        self,
        params: FilterParams,
        seed: int = 0,
        initial_capacity: int = 16,
        parallel_min_users: int = PARALLEL_MIN_USERS,
    ) -> None:
        self.params = params
        # Calls over fewer users run the kernels' serial twins (``slam_core.filter.kernels.serial``).
        self.parallel_min_users = parallel_min_users
        self.seed = seed
        start_room = min(self.MAP_START, params.anchors.capacity)
        self.state = FilterState.empty(initial_capacity, params.n_particles, start_room)
        self._slots = SlotAllocator(initial_capacity)
        self._admitted = 0
        self._type_posterior = params.anchors.type_posterior
        self._n_types = self._type_posterior.shape[0]
        # ``means``' kept rows (capacity x 2) and which slots hold a current one; None until first asked.
        self._mean: np.ndarray | None = None
        self._mean_known: np.ndarray | None = None
        self._level = np.zeros(initial_capacity, dtype=np.int64)  # each slot's floor
        self.floor_plans: dict[int, PlanIndex] = {}
        self._scratch()

    def _scratch(self) -> None:
        """``_check_users``' marks (a stamp per slot), not part of the state."""
        self._seen = np.zeros(0, dtype=np.int64)
        self._stamp = 0

    def __getstate__(self) -> dict[str, object]:
        """Pickled without its floor plans (they live in the building's store and are set again on load) and
        its scratch."""
        state = self.__dict__.copy()
        for name in ("floor_plans", "_seen", "_stamp"):
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
        self.floor_plans = {}
        self._scratch()

    # ----------------------------------------------------------------- floors
    def set_floor_plan(self, level: int, plan: PlanIndex | None) -> None:
        """The plan that weighs the steps of the users on ``level`` from now on; None: that floor has none."""
        if plan is None:
            self.floor_plans.pop(int(level), None)
        else:
            self.floor_plans[int(level)] = plan

    def plan_of(self, level: int) -> PlanIndex | None:
        """The floor's plan when it has walls or a walkable area to weigh steps by; else None."""
        plan = self.floor_plans.get(int(level))
        return plan if plan is not None and not plan.is_empty else None

    @property
    def levels(self) -> np.ndarray:
        """Each slot's floor (a slot not in use keeps its last user's)."""
        return self._level[: self.state.capacity]

    def set_levels(self, users: np.ndarray, levels: np.ndarray) -> None:
        """These users are on these floors from now on: their particles keep their places (stairs and lifts
        rise straight up), and the new floor's plan weighs their next steps."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        self._check_users(users, allow_repeats=True)
        self._level_room()
        self._level[users] = np.asarray(levels, dtype=np.int64)

    def _level_room(self) -> None:
        capacity = self.state.capacity
        if self._level.size < capacity:
            longer = np.zeros(capacity, dtype=np.int64)
            longer[: self._level.size] = self._level
            self._level = longer

    # ----------------------------------------------------------------- users
    def add_user(
        self,
        x: float,
        y: float,
        heading: float = 0.0,
        position_sigma: float = 0.5,
        crowd_map: CrowdMap | None = None,
        level: int = 0,
    ) -> int:
        """Admit a user at a start fix on floor ``level``; returns its slot. ``heading`` is used by the paper
        motion model."""
        if not all(np.isfinite([x, y, heading, position_sigma])) or position_sigma < 0:
            raise ValueError("start fix must be finite with a non-negative sigma")
        if crowd_map is not None:
            self._check_crowd_map(crowd_map)
        slot, grow_to = self._slots.allocate()
        if grow_to is not None:
            self.state = self.state.grown(grow_to)
        s = self.state
        self._level_room()
        self._level[slot] = level
        self._moved(np.array([slot]))
        s.rng_key[slot] = user_key(self.seed, self._admitted)
        s.rng_ctr[slot] = 0
        self._admitted += 1
        motion = self.params.motion
        scale_sigma = (
            motion.step_scale_sigma
            if self.plan_of(level) is None
            else self.params.floor_plan.step_scale_sigma
        )
        initialise_user(
            s.arrays(),
            slot,
            float(x),
            float(y),
            float(position_sigma),
            float(heading),
            motion.start_heading_sigma_rad,
            motion.heading_bias_sigma_rad if motion.model == "bias-scale" else 0.0,
            scale_sigma if motion.model == "bias-scale" else 0.0,
        )
        s.ctrl_cov[slot] = 0.0
        s.last_obs_heading[slot] = np.nan
        s.map_n[slot] = 0
        s.n_resamples[slot] = 0
        s.n_map_overflow[slot] = 0
        s.n_degenerate[slot] = 0
        s.active[slot] = True
        if crowd_map is not None:
            self.merge_crowd_map(np.array([slot]), crowd_map)  # seeding is a merge into an empty map
        return slot

    def add_user_among(
        self,
        candidates: np.ndarray,
        weights: np.ndarray,
        sigma: float,
        heading: float = 0.0,
        crowd_map: CrowdMap | None = None,
        level: int = 0,
    ) -> int:
        """Admit a user with no start fix, its particles spread over candidate places (beyond both papers,
        which start every user at a known position): each particle is drawn at one candidate, chosen by
        weight, plus N(0, sigma^2 I); with a floor plan, a particle outside its walkable area weighs
        ``outside_likelihood`` as much. Its draws come from the filter's seed and the user's admission."""
        candidates = np.asarray(candidates, dtype=np.float64).reshape(-1, 2)
        weights = np.asarray(weights, dtype=np.float64)
        if candidates.shape[0] == 0 or weights.shape != (candidates.shape[0],):
            raise ValueError("add_user_among needs one weight per candidate and at least one candidate")
        if not (np.all(np.isfinite(candidates)) and np.all(np.isfinite(weights)) and np.all(weights > 0)):
            raise ValueError("candidates must be finite and weights finite and positive")
        if not (math.isfinite(sigma) and sigma >= 0):
            raise ValueError("sigma must be finite and >= 0")
        p = weights / weights.sum()
        mean = p @ candidates
        admission = self._admitted
        slot = self.add_user(float(mean[0]), float(mean[1]), heading, 0.0, crowd_map, level)
        rng = np.random.default_rng([self.seed, admission, 1])
        n = self.params.n_particles
        xy = candidates[rng.choice(candidates.shape[0], size=n, p=p)] + sigma * rng.standard_normal((n, 2))
        s = self.state
        s.x[slot], s.y[slot] = xy[:, 0], xy[:, 1]
        plan = self.plan_of(level)
        if plan is not None:
            _, log_outside = self.params.floor_plan.log_weights
            logw = np.where(plan.walkable(xy), 0.0, log_outside)
            s.logw[slot] = logw - logsumexp(logw)
        return slot

    def observe_places(
        self,
        slot: int,
        centres: np.ndarray,
        weights: np.ndarray,
        sigma: float,
        outlier_probability: float,
        outlier_radius_m: float,
        inject: float = 0.0,
    ) -> None:
        """Weigh one user's particles by a multi-modal position observation (beyond both papers): a mixture
        of N(centre_j, sigma^2 I) by ``weights``, plus an outlier term uniform over a disc of
        ``outlier_radius_m``; then resample. For a phone placed from nothing, whose WiFi scan may match
        several places: across its walk the places that agree with its steps (and the floor plan) keep
        their particles. First, the ``inject`` share of its least likely particles is drawn anew among the
        centres (augmented Monte Carlo localisation), so that a cloud settled at a wrong place can still
        find the right one. NumPy, for the few users being placed."""
        self._check_users(np.array([slot]))
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
        weights = np.asarray(weights, dtype=np.float64)
        if centres.shape[0] == 0 or weights.shape != (centres.shape[0],) or not np.all(weights > 0):
            raise ValueError("observe_places needs one positive weight per centre")
        if not (np.all(np.isfinite(centres)) and sigma > 0 and 0.0 <= outlier_probability < 1.0):
            raise ValueError(
                "observe_places needs finite centres, sigma > 0 and outlier_probability in [0, 1)"
            )
        s = self.state
        self._moved(np.array([slot]))
        p = weights / weights.sum()
        n_new = int(inject * self.params.n_particles)
        if n_new:
            rng = np.random.default_rng([self.seed, int(s.rng_key[slot]), int(s.rng_ctr[slot]), 2])
            s.rng_ctr[slot] += 1  # the next injection draws anew
            worst = np.argsort(s.logw[slot])[:n_new]
            drawn = centres[rng.choice(centres.shape[0], size=n_new, p=p)] + sigma * rng.standard_normal(
                (n_new, 2)
            )
            s.x[slot, worst], s.y[slot, worst] = drawn[:, 0], drawn[:, 1]
            s.logw[slot, worst] = np.median(s.logw[slot])
        self._weigh_by_places(slot, centres, np.log(p), sigma, outlier_probability, outlier_radius_m)
        self._resample(np.array([slot]))

    def _weigh_by_places(
        self,
        slot: int,
        centres: np.ndarray,
        log_p: np.ndarray,
        sigma: float,
        outlier_probability: float,
        outlier_radius_m: float,
    ) -> None:
        """Multiply one user's particle weights by the places' likelihood, (1 - e) sum_j p_j N(centre_j;
        particle, sigma^2 I) + e / (pi r^2), in the log domain (a particle far from every centre keeps the
        outlier term, never an underflow), and normalise them. ``observe_places`` and
        ``observe_position_robust`` (one centre) weigh through it."""
        s = self.state
        var = sigma**2
        log_keep = math.log1p(-outlier_probability) - math.log(2 * math.pi * var)
        log_out = (
            math.log(outlier_probability / (math.pi * outlier_radius_m**2))
            if outlier_probability
            else -math.inf
        )
        d2 = (s.x[slot][:, None] - centres[:, 0]) ** 2 + (s.y[slot][:, None] - centres[:, 1]) ** 2
        near = np.logaddexp.reduce(log_keep + log_p - 0.5 * d2 / var, axis=1)
        logw = s.logw[slot] + np.logaddexp(near, log_out)
        s.logw[slot] = logw - np.logaddexp.reduce(logw)

    # Particle maps sized by use. The maps hold up to ``anchors.capacity`` anchors a particle (48), but a
    # state allocated for all of them costs ~0.2 MB a user however few anchors the building has, and every
    # doubling of the user slots copied all of it: ~0.4 GB at 2,048 slots, which stalled a building
    # 0.1-0.5 s while a crowd walked in. So the maps start with room for ``MAP_START`` anchors, and before
    # a kernel that may add anchors the room grows (doubling, up to the capacity) to what that call could
    # need. The kernels overflow only at the capacity, so the filters are those of maps with full room, bit
    # for bit.
    MAP_START = 4

    def _map_room(self, users: np.ndarray, new_anchors: int) -> None:
        """Room in the particle maps of ``users`` for ``new_anchors`` more anchors (up to the capacity)."""
        s = self.state
        limit = self.params.anchors.capacity
        if s.map_capacity >= limit or users.size == 0:
            return
        need = min(limit, int(s.map_n[users].max()) + new_anchors)
        if need > s.map_capacity:
            self.state = s.with_map_capacity(min(limit, max(need, 2 * s.map_capacity)))

    def _check_crowd_map(self, crowd: CrowdMap) -> None:
        if np.any((crowd.type < 0) | (crowd.type >= self._n_types)):
            raise ValueError(f"crowd map anchor types must be in [0, {self._n_types})")

    def remove_user(self, slot: int) -> None:
        self._check_users(np.array([slot]))
        self.state.active[slot] = False
        self._slots.release(slot)

    @property
    def active_users(self) -> np.ndarray:
        return np.flatnonzero(self.state.active)

    # ----------------------------------------------------------------- updates
    def step(self, users: np.ndarray, offsets: np.ndarray, lengths: np.ndarray, headings: np.ndarray) -> None:
        """Motion update (Eq. 4-8). ``users[i]`` takes steps ``offsets[i]:offsets[i+1]``; ``headings`` are the
        observed step directions (rad, counter-clockwise from east)."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        offsets = np.ascontiguousarray(offsets, dtype=np.int64)
        lengths = np.ascontiguousarray(lengths, dtype=np.float64)
        headings = np.ascontiguousarray(headings, dtype=np.float64)
        self._check_users(users)
        if offsets.shape != (users.shape[0] + 1,) or offsets[0] != 0 or np.any(np.diff(offsets) < 0):
            raise ValueError("offsets must start at 0, be non-decreasing and have len(users) + 1 entries")
        if lengths.shape != (offsets[-1],) or headings.shape != lengths.shape:
            raise ValueError("lengths and headings must have offsets[-1] entries")
        finite = np.all(np.isfinite(lengths)) and np.all(np.isfinite(headings))
        if not finite or np.any(lengths < 0):
            raise ValueError("step lengths must be finite and >= 0, headings finite")
        self._moved(users)
        self._level_room()
        levels = self._level[users]
        if users.size == 0 or levels.min() == levels.max():  # one floor: one kernel call
            self._step_on(users, offsets, lengths, headings, int(levels[0]) if users.size else 0)
            return
        counts = np.diff(offsets)
        for level in np.unique(levels).tolist():  # each floor's users under that floor's plan
            on = levels == level
            picked = np.repeat(on, counts)
            self._step_on(
                users[on],
                np.concatenate([[0], np.cumsum(counts[on])]).astype(np.int64),
                np.ascontiguousarray(lengths[picked]),
                np.ascontiguousarray(headings[picked]),
                int(level),
            )

    def _step_on(
        self, users: np.ndarray, offsets: np.ndarray, lengths: np.ndarray, headings: np.ndarray, level: int
    ) -> None:
        """The motion update of users all on ``level``, weighed by its plan."""
        s = self.state
        motion = self.params.motion
        model = MODEL_PAPER if motion.model == "paper" else MODEL_BIAS_SCALE
        plan = self.plan_of(level)
        use_plan = plan is not None
        resample = np.zeros(users.shape[0], dtype=np.bool_)
        pick(motion_update, motion_update_serial, users.shape[0], self.parallel_min_users)(
            s.arrays(),
            users,
            offsets,
            lengths,
            headings,
            (
                model,
                motion.step_length_sigma_m,
                motion.heading_change_sigma_rad,
                motion.heading_walk_sigma_rad,
                self.params.human.control_covariance_cap_m2,
            ),
            (plan or _NO_PLAN).arrays(),
            (use_plan, *self.params.floor_plan.log_weights, self.params.resampling.ess_threshold),
            resample,
        )
        if resample.any():
            self._resample(users[resample])  # particles stopped by walls give way to those in the corridors

    def observe_building_anchors(
        self, users: np.ndarray, detected_types: np.ndarray, crowd_ids: np.ndarray | None = None
    ) -> None:
        """Each user detected one building anchor of this type (Eq. 15-17, Algorithm 3); then resample.
        ``crowd_ids`` link the anchor each particle used or created to the shared map (-1: none)."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        detected_types = np.ascontiguousarray(detected_types, dtype=np.int64)
        self._check_users(users)
        if detected_types.shape != users.shape:
            raise ValueError("one detected type per user")
        if np.any((detected_types < 0) | (detected_types >= self._n_types)):
            raise ValueError(f"detected types must be in [0, {self._n_types})")
        if crowd_ids is not None:
            crowd_ids = np.ascontiguousarray(crowd_ids, dtype=np.int64)
            if crowd_ids.shape != users.shape:
                raise ValueError("one crowd id (or -1) per user")
        if users.size == 0:
            return
        self._map_room(users, 1)  # one detection a user: at most one new anchor a particle
        s = self.state
        self._moved(users)
        a = self.params.anchors
        used_slot = np.full((users.size, s.n_particles), -1, dtype=np.int64)
        pick(building_anchor_update, building_anchor_update_serial, users.shape[0], self.parallel_min_users)(
            s.arrays(),
            users,
            detected_types,
            (self._type_posterior, a.detection_sigma_m, a.new_anchor_likelihood),
            used_slot,
        )
        if crowd_ids is not None:
            self.tag_crowd_ids(users, used_slot, crowd_ids)
        self._resample(users)

    def shift(self, users: np.ndarray, dxy: np.ndarray) -> None:
        """Translate every particle of each user by ``dxy[i]`` (a revision of the user's dead-reckoned path,
        beyond the paper: see ``BuildingTracker._revise_headings``); weights, biases and maps unchanged."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        dxy = np.ascontiguousarray(dxy, dtype=np.float64).reshape(-1, 2)
        self._check_users(users)
        if dxy.shape != (users.size, 2) or not np.all(np.isfinite(dxy)):
            raise ValueError("one finite shift (dx, dy) per user")
        self._moved(users)
        self.state.x[users] += dxy[:, :1]
        self.state.y[users] += dxy[:, 1:]

    def observe_position(self, users: np.ndarray, xy: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """A position fix per user (a tag with an encoded position, a known-anchor reading, a kiosk): each
        particle is weighted by N(fix; particle, sigma^2 I), then the user is resampled. Beyond the paper,
        which has no absolute fixes after the start. A fix outside the cloud (no particle within 3 sigma of
        the combined spread) means the cloud is lost: its particles are shifted onto the fix, keeping their
        spread, bias, scale and maps, and the returned flag says so (the caller counts it).
        Returns (n,) bool: re-centred."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        xy = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 2)
        sigma = np.ascontiguousarray(sigma, dtype=np.float64)
        self._check_users(users)
        if xy.shape != (users.size, 2) or sigma.shape != users.shape:
            raise ValueError("one fix (x, y) and one sigma per user")
        if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(sigma))) or np.any(sigma <= 0):
            raise ValueError("fixes must be finite with sigma > 0")
        s = self.state
        self._moved(users)
        recentred = np.zeros(users.size, dtype=bool)
        for i, u in enumerate(users):
            d2 = (s.x[u] - xy[i, 0]) ** 2 + (s.y[u] - xy[i, 1]) ** 2
            var = sigma[i] ** 2
            if np.min(d2) > (self.params.human.gate_sigma**2) * var + 1e-12 and not self._within_cloud(
                u, xy[i]
            ):
                w = np.exp(s.logw[u] - np.max(s.logw[u]))
                w /= w.sum()
                s.x[u] += xy[i, 0] - float(w @ s.x[u])
                s.y[u] += xy[i, 1] - float(w @ s.y[u])
                recentred[i] = True
                continue
            logw = s.logw[u] - 0.5 * d2 / var
            logw -= np.logaddexp.reduce(logw)
            s.logw[u] = logw
            s.ctrl_cov[u] = 0.0
        self._resample(users[~recentred])
        return recentred

    def observe_position_robust(
        self,
        users: np.ndarray,
        xy: np.ndarray,
        sigma: float,
        outlier_probability: float,
        outlier_radius_m: float,
    ) -> None:
        """A doubtful position fix per user (a WiFi fingerprint's position): ``observe_places`` with one
        centre, each particle weighted by (1 - e) N(fix; particle, sigma^2 I) + e / (pi r^2), so that a wrong
        fix far from the cloud changes the weights almost uniformly instead of dragging the user (the
        outlier term of the human-anchor likelihood, in two dimensions). Never re-centres. Resampled by
        effective sample size, all users in one call."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        xy = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 2)
        self._check_users(users)
        if xy.shape != (users.size, 2) or not np.all(np.isfinite(xy)):
            raise ValueError("one finite fix (x, y) per user")
        if not (sigma > 0 and outlier_radius_m > 0 and 0.0 <= outlier_probability < 1.0):
            raise ValueError("sigma and outlier_radius_m must be positive, outlier_probability in [0, 1)")
        self._moved(users)
        one = np.zeros(1)  # log of a single centre's share
        for i, u in enumerate(users):
            self._weigh_by_places(int(u), xy[i : i + 1], one, sigma, outlier_probability, outlier_radius_m)
        self._resample(users)

    def observe_heading_axis(self, users: np.ndarray, stretch_heading: np.ndarray) -> None:
        """Beyond both papers: each user just walked a straight stretch whose steps pointed, as the phone
        measured them, along ``stretch_heading[i]`` (rad, counter-clockwise from east). Each particle turns
        that direction by its own heading error (its heading less the last measured step heading: its bias
        and walk in the bias-scale model) and is weighted by how close the result lies to the floor plan's
        grid (``PlanIndex.axis_rad``, modulo 90 degrees):
        s N(delta; 0, sigma^2) + (1 - s) / (pi / 2), with delta the offset from the nearest grid direction,
        so a stretch across open space changes the weights almost uniformly. Heuristic drift elimination
        (Borenstein et al., 2009) as a likelihood: particles whose bias walks the user along the corridors
        gain. Nothing happens without a plan that follows a grid (``FloorPlanParams.axis_min_strength``).
        Resampled by effective sample size."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        stretch_heading = np.ascontiguousarray(stretch_heading, dtype=np.float64)
        self._check_users(users)
        if stretch_heading.shape != users.shape or not np.all(np.isfinite(stretch_heading)):
            raise ValueError("one finite stretch heading per user")
        fp = self.params.floor_plan
        if users.size == 0 or not self.floor_plans:
            return
        self._level_room()
        axis = np.full(users.size, math.nan)  # each user's floor's grid direction (NaN: no grid to weigh by)
        for level, plan in self.floor_plans.items():
            if plan.axis_strength >= fp.axis_min_strength:
                axis[self._level[users] == level] = plan.axis_rad
        s = self.state
        measured = s.last_obs_heading[users]
        # a user without a step yet has no heading error to weigh
        keep = np.isfinite(measured) & np.isfinite(axis)
        users, stretch_heading, measured, axis = (
            users[keep],
            stretch_heading[keep],
            measured[keep],
            axis[keep],
        )
        if users.size == 0:
            return
        self._moved(users)
        quarter = 0.5 * math.pi
        error = s.heading[users] - measured[:, None]  # each particle's heading error
        delta = (stretch_heading[:, None] + error - axis[:, None] + 0.5 * quarter) % quarter - 0.5 * quarter
        var = fp.axis_sigma_rad**2
        log_on = math.log(fp.axis_share) - 0.5 * math.log(2 * math.pi * var)
        log_off = math.log((1.0 - fp.axis_share) / quarter)
        logw = s.logw[users] + np.logaddexp(log_on - 0.5 * delta**2 / var, log_off)
        s.logw[users] = logw - np.logaddexp.reduce(logw, axis=1, keepdims=True)
        self._resample(users)

    def _within_cloud(self, u: int, fix: np.ndarray) -> bool:
        """The fix lies within 3 sigma of the cloud's own spread (then weighting, not shifting, is right)."""
        row = self.summaries(np.array([u]))[0]
        cov = np.array([[row[2], row[3]], [row[3], row[4]]]) + 1e-6 * np.eye(2)
        d = fix - row[0:2]
        return float(d @ np.linalg.solve(cov, d)) <= self.params.human.gate_sigma**2

    def tag_crowd_ids(self, users: np.ndarray, used_slot: np.ndarray, crowd_ids: np.ndarray) -> None:
        """Link the anchors just used or created to the shared map's anchors (where not linked yet)."""
        s = self.state
        for i, u in enumerate(users):
            if crowd_ids[i] < 0:
                continue
            m = np.flatnonzero(used_slot[i] >= 0)
            k = used_slot[i, m]
            untagged = s.map_crowd_id[u, m, k] < 0
            s.map_crowd_id[u, m[untagged], k[untagged]] = crowd_ids[i]

    def refresh_crowd_anchors(self, users: np.ndarray, crowd: CrowdMap) -> None:
        """Overwrite every particle's copy of a shared, non-known anchor with the crowd's current estimate
        (used when the shared map is re-solved jointly and supersedes the particles' own copies)."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        self._check_users(users)
        if crowd.mean.shape[0] == 0 or users.size == 0:
            return
        s = self.state
        lookup = np.full(int(crowd.crowd_id.max()) + 1, -1, dtype=np.int64)
        lookup[crowd.crowd_id] = np.arange(crowd.crowd_id.size)
        ids = s.map_crowd_id[users]
        slot = np.arange(s.map_capacity)[None, None, :]
        row = np.where((ids >= 0) & (ids < lookup.size), lookup[np.clip(ids, 0, lookup.size - 1)], -1)
        valid = (row >= 0) & (slot < s.map_n[users][:, :, None]) & ~s.map_known[users]
        ui, mi, ki = np.nonzero(valid)
        r = row[ui, mi, ki]
        s.map_mu[users[ui], mi, ki] = crowd.mean[r]
        s.map_cov[users[ui], mi, ki] = crowd.cov[r]

    def clear_maps(self, users: np.ndarray) -> None:
        """Empty these users' particle maps (a user who changed floor: the anchors of the floor it left are
        no places of the new one; the tracker merges the new floor's crowd map next)."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        self._check_users(users)
        self.state.map_n[users] = 0

    def merge_crowd_map(self, users: np.ndarray, crowd: CrowdMap) -> None:
        """Add the shared map's anchors that a particle does not hold yet (by crowd id) to its map, so a user
        can recognise anchors that others learned after it started. Its own copies are left as they are."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        self._check_users(users)
        self._check_crowd_map(crowd)
        if crowd.mean.shape[0] == 0 or users.size == 0:
            return
        self._map_room(users, crowd.mean.shape[0])
        s = self.state
        known_var = self.params.anchors.known_sigma_m**2
        cov = crowd.cov.copy()
        cov[crowd.known] = (known_var, 0.0, known_var)
        crowd_arrays = (
            np.ascontiguousarray(crowd.mean),
            np.ascontiguousarray(cov),
            crowd.type.astype(np.int8),
            crowd.known.astype(np.bool_),
            crowd.crowd_id.astype(np.int64),
        )
        pick(merge_crowd_anchors, merge_crowd_anchors_serial, users.shape[0], self.parallel_min_users)(
            s.arrays(), users, crowd_arrays
        )

    def observe_encounters(
        self,
        user_a: np.ndarray,
        user_b: np.ndarray,
        distance: np.ndarray,
        distance_var: np.ndarray,
        offset: np.ndarray | None = None,
    ) -> EncounterOutcome:
        """Human anchors (Algorithm 1). Both users of each encounter are updated from their pre-encounter
        summaries. A user in several encounters uses the most confident peer (Section 5.1) or, with
        ``peer_selection='all'``, each in turn. Encounters failing the Mahalanobis gate are not applied.

        ``offset`` (E, 2): for an encounter measured at another time than the users' summaries describe,
        user a's displacement from then to its summary minus user b's (the tracker's: dead reckoning since,
        or a guess for a user not yet heard up to then). The distance was between the users as they were
        then, so b's summary is moved by it when it is a's anchor, and a's by its opposite when it is b's
        (the caller adds that displacement's uncertainty to ``distance_var``). None: measured now."""
        user_a = np.ascontiguousarray(user_a, dtype=np.int64)
        user_b = np.ascontiguousarray(user_b, dtype=np.int64)
        distance = np.ascontiguousarray(distance, dtype=np.float64)
        distance_var = np.ascontiguousarray(distance_var, dtype=np.float64)
        n = user_a.shape[0]
        if not (user_b.shape == distance.shape == distance_var.shape == (n,)):
            raise ValueError("user_a, user_b, distance and distance_var must have the same length")
        if offset is None:
            offset = np.zeros((n, 2))
        offset = np.ascontiguousarray(offset, dtype=np.float64)
        if offset.shape != (n, 2):
            raise ValueError(f"offset must have shape ({n}, 2), got {offset.shape}")
        self._check_users(np.concatenate([user_a, user_b]), allow_repeats=True)
        if np.any(user_a == user_b):
            raise ValueError("a user cannot encounter itself")
        if not (
            np.all(np.isfinite(distance))
            and np.all(np.isfinite(distance_var))
            and np.all(np.isfinite(offset))
        ):
            raise ValueError("distances, variances and offsets must be finite")
        if np.any(distance < 0) or np.any(distance_var <= 0):
            raise ValueError("distances must be >= 0 and variances > 0")
        if n == 0:
            return EncounterOutcome(np.zeros(0, bool), np.zeros(0))
        involved = unique_ints(np.concatenate([user_a, user_b]))
        self._moved(involved)
        summary = self.summaries(involved)
        row = {int(u): i for i, u in enumerate(involved)}
        ia = np.array([row[int(u)] for u in user_a])
        ib = np.array([row[int(u)] for u in user_b])
        mean = summary[:, 0:2]
        cov = summary[:, 2:5]
        # user-level gate: |z - ||mu_a - mu_b||| against J (Sigma_a + Sigma_b) J^T + R
        delta = mean[ia] - mean[ib] - offset  # a's position relative to b's, both as at the encounter
        d = np.hypot(delta[:, 0], delta[:, 1])
        safe = np.where(d > 1e-9, d, 1.0)
        jx = np.where(d > 1e-9, delta[:, 0] / safe, 1.0)
        jy = np.where(d > 1e-9, delta[:, 1] / safe, 0.0)
        cs = cov[ia] + cov[ib]
        var = jx * jx * cs[:, 0] + 2 * jx * jy * cs[:, 1] + jy * jy * cs[:, 2] + distance_var
        mahalanobis = np.abs(distance - d) / np.sqrt(var)
        applied = mahalanobis <= self.params.human.gate_sigma
        # directed updates (target, peer row) from pre-encounter summaries
        targets = np.concatenate([user_a[applied], user_b[applied]])
        peers = np.concatenate([ib[applied], ia[applied]])
        # each target's anchor: the peer's summary where the target's own dead reckoning since puts it now
        anchor = mean[peers] + np.concatenate([offset[applied], -offset[applied]])
        z = np.concatenate([distance[applied], distance[applied]])
        r = np.concatenate([distance_var[applied], distance_var[applied]])
        confidence = cov[peers, 0] + cov[peers, 2]
        for batch in self._peer_rounds(targets, confidence):
            self._human_update(targets[batch], anchor[batch], cov[peers[batch]], z[batch], r[batch])
        self._resample(unique_ints(targets))
        return EncounterOutcome(applied, mahalanobis)

    def _peer_rounds(self, targets: np.ndarray, confidence: np.ndarray) -> list[np.ndarray]:
        """Index sets with distinct targets: one round with each user's most confident peer, or (``all``)
        as many rounds as needed to apply every peer, most confident first."""
        order = np.lexsort((confidence, targets))
        rounds: list[list[int]] = []
        seen: dict[int, int] = {}
        for k in order:
            t = int(targets[k])
            r = seen.get(t, 0)
            seen[t] = r + 1
            if r > 0 and self.params.human.peer_selection == "most-confident":
                continue
            while len(rounds) <= r:
                rounds.append([])
            rounds[r].append(int(k))
        return [np.array(r, dtype=np.int64) for r in rounds]

    def _human_update(
        self, users: np.ndarray, peer_mean: np.ndarray, peer_cov: np.ndarray, z: np.ndarray, r: np.ndarray
    ) -> None:
        s = self.state
        h = self.params.human
        # the seven arrays it uses, not the state's bundle: a call is short, and each array passed costs its
        # dispatch
        pick(human_anchor_update, human_anchor_update_serial, users.shape[0], self.parallel_min_users)(
            s.x,
            s.y,
            s.logw,
            s.ctrl_cov,
            s.rng_key,
            s.rng_ctr,
            users,
            np.ascontiguousarray(peer_mean),
            np.ascontiguousarray(peer_cov),
            z,
            r,
            h.sampling == "iterative",
            h.beta_m,
            h.max_iterations,
            h.outlier_probability,
            h.max_range_m,
            s.n_degenerate,
        )

    def _resample(self, users: np.ndarray) -> None:
        s = self.state
        self._moved(users)
        rs = self.params.resampling
        bias_scale = self.params.motion.model == "bias-scale"  # the paper model has no bias or scale
        roughening = (rs.roughening_bias_rad, rs.roughening_scale) if bias_scale else (0.0, 0.0)
        pick(resample_users, resample_users_serial, users.shape[0], self.parallel_min_users)(
            s.arrays(),
            np.ascontiguousarray(users, dtype=np.int64),
            rs.ess_threshold,
            SCHEME_CODES[rs.scheme],
            roughening,
        )

    # ----------------------------------------------------------------- estimates
    def summaries(self, users: np.ndarray) -> np.ndarray:
        """(n, 8) rows of SUMMARY_FIELDS: weighted mean, its covariance, the max-weight particle, heading."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        self._check_users(users, allow_repeats=True)
        out = np.empty((users.shape[0], len(SUMMARY_FIELDS)))
        s = self.state
        pick(summarise, summarise_serial, users.shape[0], self.parallel_min_users)(
            s.x, s.y, s.heading, s.logw, users, out
        )
        return out

    def means(self, users: np.ndarray) -> np.ndarray:
        """(n, 2) weighted means: ``summaries(users)[:, 0:2]``, exactly. A user's mean is kept until its
        particles change (``_moved``): the encounter selection asks for the means of every user a call's
        detections name, most of whom this call did not touch."""
        users = np.ascontiguousarray(users, dtype=np.int64)
        self._check_users(users, allow_repeats=True)
        s = self.state
        kept, known = self._mean, self._mean_known
        if kept is None or known is None or known.size != s.capacity:  # new, or the state grew
            kept, known = np.empty((s.capacity, 2)), np.zeros(s.capacity, dtype=bool)
            self._mean, self._mean_known = kept, known
        stale = unique_ints(users[~known[users]])
        if stale.size:
            out = np.empty((stale.size, 2))
            pick(weighted_means, weighted_means_serial, stale.shape[0], self.parallel_min_users)(
                s.x, s.y, s.logw, stale, out
            )
            kept[stale] = out
            known[stale] = True
        result: np.ndarray = kept[users]
        return result

    def _moved(self, users: np.ndarray) -> None:
        """These users' particles (positions or weights) are about to change: their kept means are stale.
        Every method that changes ``x``, ``y`` or ``logw`` calls it first."""
        known = self._mean_known
        if known is not None and known.size != self.state.capacity:  # the state grew: start afresh
            self._mean_known = None
        elif known is not None:
            known[users] = False

    def _check_users(self, users: np.ndarray, allow_repeats: bool = False) -> None:
        if users.ndim != 1:
            raise ValueError("users must be a 1-D array of slots")
        if users.size == 0:
            return
        active = self.state.active
        if self._seen.size != active.size:  # the state grew
            self._seen = np.zeros(active.size, dtype=np.int64)
        self._stamp += 1
        problem = slots_problem(users, active, self._seen, self._stamp, allow_repeats)
        if problem == UNKNOWN:
            raise ValueError(f"unknown user slot in {users.tolist()[:10]}")
        if problem == REPEATED:
            raise ValueError("a user may appear only once per call")
