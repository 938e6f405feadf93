"""One building's tracking: every user's DynamicSLAM filter, the crowd anchor map and online encounters.

``BuildingTracker.apply`` takes the arrays of one or more users' batches (already validated and converted
by the server) and advances everything they imply, in this order:

0. raw IMU of users who do not count their own steps goes through the sensor front-end
   (``slam_core.sensing.front_end``: online PDR and the building-anchor detectors, state carried per user
   between batches) and becomes steps and anchor detections;
1. each user's events in time order: a first position fix starts its filter (seeded from the crowd map);
   steps move it (Eq. 4-8); a building-anchor detection feeds the crowd map with the user's pre-update
   estimate and updates the filter (Eq. 15-17, Algorithm 3); a detection of an identified transmitter
   (a signature anchor) joins its crowd anchor by identity and, once other users have placed that anchor,
   is a gated position measurement of the user; a later fix reweights it. Users are advanced
   together, one tracker call per round of events, so a micro-batch of many phones costs one kernel call;
2. the crowd map is re-solved jointly (every ``graph_solve_period_ms`` of phone time) and new anchors are
   offered to every user; with fingerprint fixes on, each user's latest scan the crowd's WiFi fingerprint
   map can place is a robust position fix, and confident users' scans join that map;
3. WiFi scans and Bluetooth sightings are matched against the building's other users (Eq. 3, the RSS
   cut-off); detections between tracked users that the selector chooses from the filters' estimates
   (``slam_core.encounters.selection``) become human anchors (Algorithm 1), both users updated from their
   pre-encounter states, each reading placed at its time (the users' dead reckoning since, or a guess for a
   peer whose phone has not reported up to it yet);
Every user is on one floor at a time: the tracker keeps a belief over the building's floors per user
(``slam_core.tracking.floors``), started by the floor a fix names, moved by changes of height (a detection
that carries a rise), and weighed by each floor's fingerprint map; the believed floor decides the plan, the
anchors, the fingerprints and the encounters a user has.

4. the estimate of every user whose batch was applied. A peer that an encounter moved is not estimated
   here: its estimate comes with its own next batch (within a sighting period), so that every batch yields
   one estimate, however many encounters it makes.

The signature, fingerprint and encounter stages are objects the tracker owns
(``slam_core.tracking.signature_stage``, ``fingerprint_stage``, ``encounter_stage``); the per-user dead
reckoning lives in ``slam_core.tracking.trails``, the rounds of events in ``slam_core.tracking.rounds``.

Pure numerics: no I/O, no clock. Times are the phones' epoch milliseconds.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from slam_core.crowd.anchor_map import CrowdMapBuilder
from slam_core.crowd.fingerprints import NOBODY
from slam_core.crowd.graph import CrowdGraph, CrowdGraphParams
from slam_core.encounters.models import Calibration
from slam_core.filter.dynamic_slam import CrowdMap, DynamicSlam
from slam_core.filter.floor_plan import PlanIndex
from slam_core.filter.kernels.linalg2 import largest_eigenvalue2
from slam_core.sensing.detectors import AnchorEvents, DetectorParams
from slam_core.sensing.front_end import FrontEnd, RadioArrays
from slam_core.tracking.batches import (
    EncounterResult,
    EstimateRow,
    TrackerOutcome,
    UserBatch,
    UserReport,
)
from slam_core.tracking.encounter_stage import EncounterStage
from slam_core.tracking.fingerprint_stage import FingerprintStage
from slam_core.tracking.floor_stage import FloorStage
from slam_core.tracking.params import CROWD_SOLVERS, TrackerParams
from slam_core.tracking.rounds import Round, lay_steps, round_at
from slam_core.tracking.signature_stage import SignatureStage
from slam_core.tracking.stretches import StraightStretches
from slam_core.tracking.trails import Trails, UserTrack
from slam_core.tracking.zone_stage import ZoneStage

CLOCK_JUMP_BACK_MS = 60_000
"""A batch whose every time is this far behind its user's last one: the phone's clock went back (set by hand,
a reset), and the user's timeline restarts there (``BuildingTracker._restart_timeline``)."""

__all__ = [
    "CROWD_SOLVERS",
    "BuildingTracker",
    "EncounterResult",
    "EstimateRow",
    "TrackerOutcome",
    "TrackerParams",
    "UserBatch",
    "UserReport",
]


class BuildingTracker:
    def __init__(self, params: TrackerParams, calibration: Calibration, seed: int = 0) -> None:
        self.params = params
        fp = params.filter
        self.filters = DynamicSlam(fp, seed=seed)
        self.crowd = CrowdMapBuilder(
            fp.anchors.type_posterior,
            fp.anchors.detection_sigma_m,
            fp.anchors.new_anchor_likelihood,
            fuse=params.crowd_solver == "fusion",
        )
        self.graph = CrowdGraph(CrowdGraphParams(detection_sigma_m=fp.anchors.detection_sigma_m))
        self.signatures = SignatureStage(params, self.crowd, self.graph)
        self.fingerprints = FingerprintStage(params.fingerprints, params.detection.stale_ap_ms, params.floors)
        self.floor_stage = FloorStage(params.floors)
        self.zones = ZoneStage(params.zones)
        self.encounters = EncounterStage(params, calibration)
        self._users: dict[str, UserTrack] = {}
        self.trails = Trails()  # the tracked users' recent steps, by filter slot
        self.front_end = FrontEnd(params.pdr, params.detectors)
        vertical = (params.detectors or DetectorParams()).vertical
        self._escalator_type = vertical.escalator_type
        self._vertical_types = frozenset(
            (vertical.elevator_type, vertical.stairs_type, vertical.escalator_type)
        )
        self._by_ble: dict[str, str] = {}
        self._last_solve_ms: dict[int, int] = {}  # by floor: each floor's crowd map is solved on its own
        self._graph_users: list[int] = []
        self._started = 0
        self.n_types = fp.anchors.type_posterior.shape[0]
        plan = fp.floor_plan
        self._stretches = StraightStretches(plan.stretch_m, plan.stretch_turn_rad)

    @property
    def radio_map_id(self) -> str | None:
        """The signal-map build whose radio map the fingerprints hold (None: none loaded)."""
        return self.fingerprints.radio_map_id

    def load_radio_map(
        self,
        map_id: str,
        xy: np.ndarray,
        bssids: list[list[str]],
        rss: list[np.ndarray],
        t_ms: np.ndarray,
        levels: np.ndarray | None = None,
    ) -> int:
        """``FingerprintStage.load_radio_map``: a signal-map build's scans join their floors' fingerprints
        (``levels`` per scan, None: floor 0; a floor the building does not have: ValueError naming its
        floors)."""
        for level in set(() if levels is None else np.asarray(levels).tolist()):
            self.floor_stage.index(level)
        return self.fingerprints.load_radio_map(map_id, xy, bssids, rss, t_ms, levels)

    def set_floor_plan(self, plan: PlanIndex | None, level: int = 0) -> None:
        """The plan that weighs the steps of the users on floor ``level`` from now on (beyond the papers);
        None: that floor has none."""
        self.floor_stage.index(level)
        self.filters.set_floor_plan(level, plan)

    @property
    def levels(self) -> tuple[int, ...]:
        """The building's floors, lowest first."""
        return self.floor_stage.levels

    def set_levels(self, levels: tuple[int, ...], elevations_m: tuple[float, ...] | None = None) -> None:
        """The building's floors (and their heights where known; NaN: from the storey height). A user's belief
        keeps its share on the floors that stay; a floor taken away takes its users' share with it (a user
        left with nothing starts over, unsure among all floors)."""
        self.floor_stage.set_levels(levels, elevations_m)
        self._follow_floors([n for n, u in self._users.items() if u.slot >= 0])

    def floor_of(self, user: str) -> tuple[int, float]:
        """The floor the user is believed on and the belief's probability."""
        return self.floor_stage.believed(user)

    # ------------------------------------------------------------------ users and anchors
    @property
    def users(self) -> list[str]:
        return list(self._users)

    def is_tracking(self, user: str) -> bool:
        """Whether the user has a filter (started by a fix, or being placed by the crowd's map)."""
        u = self._users.get(user)
        return u is not None and u.slot >= 0

    def is_placed(self, user: str) -> bool:
        """Whether the user is tracked and its position is reported: started by a fix, or a cold start whose
        estimate has become confident (``ColdStartParams``)."""
        u = self._users.get(user)
        return u is not None and u.slot >= 0 and u.placed

    def last_time_ms(self, user: str) -> int:
        u = self._users.get(user)
        return -1 if u is None else u.last_t_ms

    def remove_user(self, user: str) -> None:
        """Forget a user (idle or gone); its filter slot is freed. Its crowd-map contributions stay."""
        self.remove_users([user])

    def remove_users(self, users: list[str]) -> None:
        """Forget these users (``remove_user`` for many: the Bluetooth index is rebuilt once)."""
        unknown = [n for n in users if n not in self._users]
        if unknown:
            raise KeyError(f"unknown users {unknown!r}")
        for name in users:
            u = self._users.pop(name)
            self.front_end.forget(name)
            self._stretches.forget(name)
            self.floor_stage.leave(name)
            if u.slot >= 0:
                self.filters.remove_user(u.slot)
                self.encounters.remove(name)
                self.trails.release(u.slot)
                self.zones.release(np.array([u.slot]))
        gone = set(users)
        self._by_ble = {k: v for k, v in self._by_ble.items() if v not in gone}

    def pin_anchor(self, xy: np.ndarray, anchor_type: int, index: int | None = None, level: int = 0) -> int:
        """Add an operator-known anchor on floor ``level`` (or pin an existing one there); returns its crowd
        index."""
        self._check_type(anchor_type)
        self.floor_stage.index(level)
        if index is None:
            index = self.crowd.add_known(xy, anchor_type, level)
        else:
            self.crowd.pin(index, xy, anchor_type, level)
        self.graph.set_known(index, np.asarray(xy, dtype=float))
        self._offer_crowd_map()
        return index

    def restore_anchor(
        self,
        xy: np.ndarray,
        cov: np.ndarray,
        anchor_type: int,
        known: bool,
        observations: int,
        t_ms: int,
        signature: str = "",
        level: int = 0,
    ) -> int:
        self._check_type(anchor_type)
        index = self.crowd.restore(xy, cov, anchor_type, known, observations, float(t_ms), signature, level)
        if known:
            self.graph.set_known(index, np.asarray(xy, dtype=float))
        return index

    def remove_anchor(self, index: int) -> None:
        self.crowd.remove(index)

    def merge_anchors(self, keep: int, drop: int) -> None:
        self.crowd.merge(keep, drop)
        self.graph.relabel(drop, keep)

    def _check_type(self, anchor_type: int) -> None:
        if not 0 <= anchor_type < self.n_types:
            raise ValueError(f"anchor type must be in [0, {self.n_types})")

    def displacement(self, user: str) -> np.ndarray | None:
        """The user's dead-reckoned displacement since its start, as its applied steps integrate it (not
        re-rotated): the difference between two calls is what the motion update moved it by."""
        u = self._users.get(user)
        if u is None or u.slot < 0:
            return None
        return u.displacement.copy()

    def dead_reckoning(self, user: str) -> np.ndarray | None:
        """Plain PDR: the user's starting fix plus every applied step, ignoring every observation (the
        baseline the filter is measured against). Steps from the PDR front-end's gyroscope heading are
        re-rotated by its latest north offset: the offset is one constant error whose estimate improves as
        the walk goes on (``slam_core.sensing.pdr.heading``), so the best causal guess of the path walked so
        far turns all of it, not only the steps still to come."""
        u = self._users.get(user)
        if u is None or u.slot < 0:
            return None
        if not math.isfinite(u.heading_offset):
            position: np.ndarray = u.origin + u.displacement
            return position
        c, s = math.cos(u.heading_offset), math.sin(u.heading_offset)
        gx, gy = u.gyro_displacement  # azimuth offset clockwise = a clockwise turn of the relative path
        turned: np.ndarray = u.origin + np.array([c * gx + s * gy, -s * gx + c * gy])
        return turned

    def estimate(self, user: str) -> EstimateRow | None:
        u = self._users.get(user)
        if u is None or u.slot < 0:
            return None
        return self._rows([user])[user]

    # ------------------------------------------------------------------ the batch path
    def apply(self, batches: list[UserBatch]) -> TrackerOutcome:
        """Advance the building by these users' batches (at most one per user)."""
        names = [b.user for b in batches]
        if len(set(names)) != len(names):
            raise ValueError("at most one batch per user per call")
        for b in batches:
            if b.detect_type.size and np.any((b.detect_type < 0) | (b.detect_type >= self.n_types)):
                raise ValueError(f"user batch of {b.user!r}: anchor type outside [0, {self.n_types})")
            for level in set(b.fix_level.tolist()):
                # a floor the building does not have: ValueError naming its floors
                self.floor_stage.index(level)
        reports = {b.user: UserReport() for b in batches}
        for b in batches:
            u = self._users.get(b.user)
            latest = _latest_time(b)
            if u is not None and u.last_t_ms >= 0 and 0 <= latest < u.last_t_ms - CLOCK_JUMP_BACK_MS:
                self._restart_timeline(b.user, u)
                reports[b.user].clock_restarted = True
        batches = [self._dead_reckon(b, reports[b.user]) for b in batches]
        for b in batches:
            if b.user not in self._users:  # unsure of its floor until a fix names it or the radio tells
                self._users[b.user] = UserTrack()
                self.floor_stage.join(b.user)
            if b.ble_id is not None:
                self._by_ble[b.ble_id] = b.user
        callers = [self._users[b.user] for b in batches]
        self.encounters.begin(callers)
        rounds = self._plan(batches, reports)
        newest = max([self._users[b.user].last_t_ms for b in batches], default=-1)
        # in a busy call the scans are compared on a thread while the rounds and the fingerprint fixes
        # run: the detector depends on nothing they change
        scans = self.encounters.start(batches)
        try:
            changed = self._observe(batches, rounds, reports, newest)
            self._observe_places(batches, reports)
            self.encounters.heard(callers, [_heard_until(b) for b in batches], self.trails)
            encounters, detections = self.encounters.collect(
                self.filters, batches, self._users, self._by_ble, scans, self.trails
            )
        finally:
            scans.join()
        self._confirm_placements([b.user for b in batches])
        for b in batches:
            tracked = self.is_tracking(b.user)
            placed = tracked and self._users[b.user].placed
            reports[b.user].status = "tracking" if placed else ("placing" if tracked else "awaiting_fix")
        estimates = self._rows(sorted(b.user for b in batches if reports[b.user].status == "tracking"))
        for user, row in estimates.items():  # an output is kept only finite: the caller then undoes the call
            if not all(math.isfinite(v) for v in (row.x, row.y, *row.cov, *row.best, row.heading)):
                raise ValueError(f"user {user!r}: the filter's estimate is not finite")
        zone_events = (
            self.zones.update(
                self.filters,
                list(estimates),
                np.array([self._users[n].slot for n in estimates], dtype=np.int64),
                np.array([row.t_ms for row in estimates.values()], dtype=np.int64),
            )
            if len(self.zones)
            else []
        )
        return TrackerOutcome(reports, estimates, encounters, sorted(changed), detections, zone_events)

    def _confirm_placements(self, names: list[str]) -> None:
        """Users being placed whose estimate is now confident count as placed (for good)."""
        placing = [n for n in names if self.is_tracking(n) and not self._users[n].placed]
        if not placing:
            return
        limit = self.params.cold_start.confident_sigma_m**2
        for name, row in self._rows(placing).items():
            if largest_eigenvalue2(*row.cov) <= limit:
                self._users[name].placed = True

    def _restart_timeline(self, user: str, u: UserTrack) -> None:
        """The phone's clock went back: its user's timeline restarts at its next event (its filter, position
        and maps kept), instead of every step being skipped as out of order until the clock catches up.
        Readings from before the jump can no longer be placed on its trail."""
        u.last_t_ms = -1
        self.front_end.forget(user)
        self._stretches.forget(user)
        if u.slot >= 0:
            self.encounters.restart(u.slot)
            self.trails.reset(u.slot)

    def _observe(
        self, batches: list[UserBatch], rounds: list[Round], reports: dict[str, UserReport], newest: int
    ) -> set[int]:
        """The rounds of steps and anchor events, the crowd map's solve, and the fingerprint fixes; returns
        the crowd anchors changed."""
        changed: set[int] = set()
        crowd_size = len(self.crowd)
        for rnd in rounds:
            self._run_round(rnd, reports, changed)
        if self.params.crowd_solver == "graph" and changed:
            self._solve_crowd_map(changed, newest)
        if len(self.crowd) != crowd_size:
            self._offer_crowd_map()
        if self.params.fingerprints.enabled:
            names = [b.user for b in batches if self.is_tracking(b.user) and b.scan_t.size]
            rows = self._rows(names)
            if not self.floor_stage.single:
                self._weigh_floors(batches, rows)
                rows = self._rows(names)
            self.fingerprints.fix(self.filters, batches, self._users, rows, reports, self.trails)
        return changed

    def _solve_crowd_map(self, changed: set[int], newest: int) -> None:
        """The joint solve of the crowd's map (``CrowdGraph``) on the floors whose anchors changed, at most
        every ``graph_solve_period_ms`` of phone time a floor; the solved floors' users take its estimates
        into their particles' maps (which overwrites their own copies: a floor whose map did not change keeps
        them, as it would in a building of that floor alone). Adds the re-estimated anchors to ``changed``."""
        crowd, period = self.crowd, self.params.graph_solve_period_ms
        levels = {crowd.level(c) for c in changed if crowd.is_live(c)}
        due = {lv for lv in levels if newest - self._last_solve_ms.get(lv, -(2**62)) >= period}
        if not due:
            return
        initial = crowd.means()
        on_due = {c for c in initial if crowd.level(c) in due}
        means, covs = self.graph.solve(initial, on_due)
        solved = due | {crowd.level(c) for c in means if crowd.is_live(c)}
        for lv in solved:
            self._last_solve_ms[lv] = newest
        for c, mean in means.items():
            if crowd.is_live(c):
                crowd.set_estimate(c, mean, covs[c])
                changed.add(c)
        for users, level in self._by_level(self.filters.active_users):
            if level in solved:
                self.filters.refresh_crowd_anchors(users, crowd.snapshot(level))

    def _by_level(self, slots: np.ndarray) -> list[tuple[np.ndarray, int]]:
        """The slots grouped by the floor they are on (one group in a one-floor building)."""
        if not slots.size:
            return []
        levels = self.filters.levels[slots]
        if levels.min() == levels.max():
            return [(slots, int(levels[0]))]
        return [(slots[levels == lv], int(lv)) for lv in np.unique(levels).tolist()]

    def _weigh_floors(self, batches: list[UserBatch], rows: dict[str, EstimateRow]) -> None:
        """Each tracked user's latest scan weighs its floor belief by the floors' fingerprint maps near its
        estimate (``FingerprintStage.floor_evidence``); users whose believed floor changes follow it."""
        stale = self.params.detection.stale_ap_ms
        moved = []
        for b in batches:
            row = rows.get(b.user)
            if row is None:
                continue
            u = self._users[b.user]
            _, bssids, rss = b.fresh_scan(int(np.argmax(b.scan_t)), stale)
            ll = self.fingerprints.floor_evidence(
                self.floor_stage.levels, u.number, bssids, rss, np.array([row.x, row.y])
            )
            if self.floor_stage.weigh_near(b.user, row.floor, ll):
                moved.append(b.user)
        self._follow_floors(moved)

    def _follow_floors(self, names: list[str]) -> None:
        """Users whose believed floor is not the one their filter is on move to it: their particles keep their
        places, their maps take the new floor's anchors."""
        changing = []
        for name in names:
            u = self._users[name]
            if u.slot < 0:
                continue
            level, _ = self.floor_stage.believed(name)
            if int(self.filters.levels[u.slot]) != level:
                changing.append((u.slot, level))
        if not changing:
            return
        slots = np.array([c[0] for c in changing], dtype=np.int64)
        self.filters.set_levels(slots, np.array([c[1] for c in changing], dtype=np.int64))
        self.filters.clear_maps(slots)
        for users, level in self._by_level(slots):
            self.filters.merge_crowd_map(users, self.crowd.snapshot(level))

    def _dead_reckon(self, b: UserBatch, report: UserReport) -> UserBatch:
        """The batch with the steps the PDR front-end finds in its raw IMU (phones counting their own steps
        and batches without IMU pass through)."""
        if b.imu is None:
            return b
        imu = b.imu
        if b.step_t.size or not (imu.acc.size or imu.gyr.size or imu.rv.size or imu.grv.size):
            # a phone that counts its own steps: its barometer, if it sent one, still finds floor changes
            if not imu.pressure.size:
                return replace(b, imu=None)
            own = bool(
                b.detect_rise.size and np.isfinite(b.detect_rise).any()
            )  # the phone finds floors itself
            events, dropped = self.front_end.floor_changes(b.user, imu.pressure, b.step_t, own)
            report.imu_samples_dropped = dropped
            report.anchors_detected = events.t_ms.size
            return replace(b, imu=None, **_with_detections(b, events))
        heard = RadioArrays(
            b.scan_t, b.scan_offsets, b.scan_bssid, b.scan_rss, b.scan_last_seen,
            b.beacon_t, b.beacon_mac, b.beacon_rss,
        )  # fmt: skip
        out = self.front_end.process(b.user, b.imu, heard)
        report.imu_samples_dropped = out.imu_samples_dropped
        report.steps_detected = out.steps.t_ms.size
        report.anchors_detected = out.anchors.t_ms.size
        return replace(
            b,
            step_t=out.steps.t_ms,
            step_length=out.steps.length_m,
            step_azimuth=out.steps.azimuth_rad,
            step_turn=out.steps.turn_rad,
            step_heading_offset=out.steps.heading_offset_rad,
            imu=None,
            **_with_detections(b, out.anchors),
        )

    def _plan(self, batches: list[UserBatch], reports: dict[str, UserReport]) -> list[Round]:
        """Each user's events in time order, cut into rounds at every observation (detection or fix)."""
        rounds: list[Round] = []
        crowd_maps: dict[int, CrowdMap] = {}  # each floor's crowd map for this call's new users: built once
        for b in batches:
            u = self._users[b.user]
            report = reports[b.user]
            # (time, kind order, index): fixes first at equal times, then steps, then detections; a phone with
            # no fix yet may be placed at its first scan the crowd's map can place (index -1)
            placing = None if u.slot >= 0 or b.fix_t.size else self._cold_start_at(b)
            events = sorted(
                [(int(t), 0, i) for i, t in enumerate(b.fix_t)]
                + ([] if placing is None else [(placing[0], 0, -1)])
                + [(int(t), 1, i) for i, t in enumerate(b.step_t)]
                + [(int(t), 2, i) for i, t in enumerate(b.detect_t)]
            )
            r = 0
            lengths: list[float] = []
            headings: list[float] = []
            times: list[int] = []
            offsets: list[float] = []
            started = u.slot >= 0
            for t, kind, i in events:
                if t < u.last_t_ms or (t == u.last_t_ms and kind == 1):
                    report.steps_dropped += kind == 1
                    continue
                if kind == 1:
                    heading = self._step_heading(u, b, i)
                    if not started or not math.isfinite(heading):
                        report.steps_dropped += 1
                        continue
                    u.heading = heading
                    u.last_t_ms = t
                    lengths.append(float(b.step_length[i]))
                    headings.append(heading)
                    times.append(t)
                    offsets.append(
                        float(b.step_heading_offset[i]) if b.step_heading_offset.size else math.nan
                    )
                    continue
                rnd = round_at(rounds, r)
                if lengths:
                    rnd.add_steps(b.user, lengths, headings, times, offsets)
                    report.steps_applied += len(lengths)
                    lengths, headings, times, offsets = [], [], [], []
                if kind == 0 and i < 0:
                    assert placing is not None
                    self._start_among(b.user, placing[1], placing[2], placing[3], crowd_maps)
                    started = True
                    report.cold_started = True
                elif kind == 0:
                    if not started:
                        self._start(
                            b.user,
                            b.fix_xy[i],
                            float(b.fix_sigma[i]),
                            float(b.fix_azimuth[i]),
                            b.fix_floor(i),
                            crowd_maps,
                        )
                        started = True
                    else:
                        rnd.fix_users.append(b.user)
                        rnd.fix_xy.append(b.fix_xy[i])
                        rnd.fix_sigma.append(float(b.fix_sigma[i]))
                        rnd.fix_level.append(b.fix_floor(i))
                    report.fixes_applied += 1
                elif started:
                    rnd.det_users.append(b.user)
                    rnd.det_types.append(int(b.detect_type[i]))
                    rnd.det_rise.append(b.rise(i))
                    rnd.det_t.append(t)
                    rnd.det_signature.append(b.detect_signature[i] if b.detect_signature else "")
                    rnd.det_observed_t.append(int(b.detect_observed_t[i]) if b.detect_observed_t.size else t)
                    report.detections_applied += 1
                u.last_t_ms = t
                r += 1
            if lengths:
                round_at(rounds, r).add_steps(b.user, lengths, headings, times, offsets)
                report.steps_applied += len(lengths)
        return rounds

    def _step_heading(self, u: UserTrack, b: UserBatch, i: int) -> float:
        """The step's direction, counter-clockwise from east: from the azimuth when given, else the last
        heading plus the turn (NaN when neither is known)."""
        azimuth = float(b.step_azimuth[i])
        if math.isfinite(azimuth):
            return math.pi / 2 - azimuth
        turn = float(b.step_turn[i])
        if math.isfinite(turn) and math.isfinite(u.heading):
            return u.heading + turn
        return math.nan

    def _observe_places(self, batches: list[UserBatch], reports: dict[str, UserReport]) -> None:
        """Users being placed: their latest scan's candidate places weigh their particles as a mixture
        (``DynamicSlam.observe_places``), except in the call that started them from those places."""
        cold = self.params.cold_start
        fp = self.params.fingerprints
        for b in batches:
            u = self._users[b.user]
            if u.slot < 0 or u.placed or reports[b.user].cold_started:
                continue
            found = self._candidates(b, latest=True)
            if found is not None:
                _, centres, weights, _ = found
                self.filters.observe_places(
                    u.slot,
                    centres,
                    weights,
                    cold.candidate_sigma_m,
                    fp.outlier_probability,
                    fp.outlier_radius_m,
                    cold.inject,
                )

    def _cold_start_at(self, b: UserBatch) -> tuple[int, np.ndarray, np.ndarray, int] | None:
        """The first of the batch's scans the crowd's fingerprint maps can place: (its time, the candidate
        places, their weights, their floor); None when cold starts are off or no scan can be placed. The
        floor comes first: the user's belief, weighed by the floors' maps (each floor's nearest reference,
        anywhere on it), picks the floor whose map then places the scan."""
        if not (self.params.cold_start.enabled and self.params.fingerprints.enabled):
            return None
        if not self.floor_stage.single and b.scan_t.size:
            stale = self.params.detection.stale_ap_ms
            self.floor_stage.weigh_scans(
                b.user,
                (b.fresh_scan(int(c), stale)[1:] for c in np.argsort(b.scan_t, kind="stable").tolist()),
                lambda levels, bssids, rss: self.fingerprints.floor_evidence(
                    levels, NOBODY, bssids, rss, None
                ),
            )
        return self._candidates(b, latest=False)

    def _candidates(self, b: UserBatch, latest: bool) -> tuple[int, np.ndarray, np.ndarray, int] | None:
        """The first (or latest) of the batch's scans the fingerprint map of the user's floor can place: its
        time, candidate places, their weights and the floor. A cold start waits for a scan whose candidates
        agree (within the fingerprint fixes' ``max_spread_m``): where the map does not know the place, its
        nearest places in signal space are anywhere; a user being placed is weighed by every scan's."""
        if not b.scan_t.size:
            return None
        level = self.floor_stage.believed(b.user)[0]
        spread = math.inf if latest else self.params.fingerprints.max_spread_m
        stale = self.params.detection.stale_ap_ms
        order = np.argsort(b.scan_t, kind="stable")
        for c in order[::-1] if latest else order:
            t, bssids, rss = b.fresh_scan(int(c), stale)
            found = self.fingerprints.candidates(level, bssids, rss, spread)
            if found is not None:
                return t, found[0], found[1], level
        return None

    def _crowd_map(self, level: int, built: dict[int, CrowdMap]) -> CrowdMap:
        """The crowd's map of a floor for a new user's particles, built once per floor in ``built`` (the
        anchors do not change while a call admits its users)."""
        found = built.get(level)
        if found is None:
            found = built[level] = self.crowd.snapshot(level)
        return found

    def _start_among(
        self, user: str, candidates: np.ndarray, weights: np.ndarray, level: int, built: dict[int, CrowdMap]
    ) -> None:
        """Start a user with no fix over the crowd's candidate places on a floor; it is placed once
        confident."""
        u = self._users[user]
        sigma = self.params.cold_start.candidate_sigma_m
        slot = self.filters.add_user_among(
            candidates, weights, sigma, 0.0, self._crowd_map(level, built), level=level
        )
        u.placed = False
        self._admit(user, slot, (weights / weights.sum()) @ candidates)

    def _start(
        self, user: str, xy: np.ndarray, sigma: float, azimuth: float, level: int, built: dict[int, CrowdMap]
    ) -> None:
        u = self._users[user]
        heading = math.pi / 2 - azimuth if math.isfinite(azimuth) else 0.0
        if math.isfinite(azimuth):
            u.heading = heading
        sigma = max(sigma, self.params.start_sigma_floor_m)
        self.floor_stage.start(user, level)
        slot = self.filters.add_user(
            float(xy[0]), float(xy[1]), heading, sigma, self._crowd_map(level, built), level=level
        )
        u.placed = True
        self._admit(user, slot, xy)

    def _admit(self, user: str, slot: int, xy: np.ndarray) -> None:
        u = self._users[user]
        u.slot = slot
        self.encounters.admit(user, u.slot)
        self.trails.reset(slot)
        u.number = self._started
        u.origin = np.asarray(xy, dtype=float).copy()
        self._started += 1
        self.graph.add_user(u.number, np.asarray(xy, dtype=float))
        self._graph_users.append(u.number)
        while len(self._graph_users) > self.params.max_graph_users:
            self.graph.forget_user(self._graph_users.pop(0))

    def _run_round(self, rnd: Round, reports: dict[str, UserReport], changed: set[int]) -> None:
        if rnd.users:
            users = [self._users[n] for n in rnd.users]
            counts = [len(x) for x in rnd.step_len]
            offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
            lengths = np.concatenate(rnd.step_len)
            headings = np.concatenate(rnd.step_head)
            self.filters.step(np.array([u.slot for u in users], dtype=np.int64), offsets, lengths, headings)
            lay_steps(users, rnd, lengths, headings, self.trails)
            if self.params.revise_headings:
                self._revise_headings(users)
            if self.params.filter.floor_plan.heading_axes and self.filters.floor_plans:
                self._observe_stretches(rnd)
        plain = [k for k, s in enumerate(rnd.det_signature) if not s]
        signed = [k for k, s in enumerate(rnd.det_signature) if s]
        if plain:
            names = [rnd.det_users[k] for k in plain]
            types = [rnd.det_types[k] for k in plain]
            rising = [
                (n, rnd.det_rise[k], rnd.det_types[k])
                for n, k in zip(names, plain, strict=True)
                if math.isfinite(rnd.det_rise[k])
            ]
            if rising:  # a change of floor: the anchor is the landing, on the floor arrived at
                for name, rise, _ in rising:
                    self.floor_stage.rise(name, rise)  # the crowd measures the storeys
                self._follow_floors([n for n, _, _ in rising])
                self._carry([(n, r) for n, r, t in rising if t == self._escalator_type])
            unmeasured = [
                n
                for n, k in zip(names, plain, strict=True)
                if not math.isfinite(rnd.det_rise[k])
                and rnd.det_types[k] in self._vertical_types
                and not self.front_end.has_barometer(n)
            ]
            if unmeasured:  # a phone without a barometer at stairs, a lift or an escalator: maybe a new floor
                for name in unmeasured:
                    self.floor_stage.maybe_changed(name)
            slots = np.array([self._users[n].slot for n in names], dtype=np.int64)
            before = self.filters.summaries(slots)
            levels = self.filters.levels[slots].tolist()
            ids = []
            for name, row, f, k, level in zip(names, before, types, plain, levels, strict=True):
                cov = np.array([[row[2], row[3]], [row[3], row[4]]])
                ids.append(
                    self.crowd.contribute(
                        self._users[name].number, row[0:2], cov, f, float(rnd.det_t[k]), level
                    )
                )
                reports[name].anchor_joins.append((rnd.det_t[k], ids[-1]))
            self.filters.observe_building_anchors(slots, np.array(types), np.array(ids))
            for name in names:
                self._users[name].pin()
            self._add_to_graph(names, ids, changed)
        if signed:
            changed.update(
                self.signatures.observe(self.filters, self._users, rnd, signed, reports, self.trails)
            )
        if rnd.fix_users:
            slots = np.array([self._users[n].slot for n in rnd.fix_users], dtype=np.int64)
            recentred = self.filters.observe_position(slots, np.array(rnd.fix_xy), np.array(rnd.fix_sigma))
            for name, flag, level in zip(rnd.fix_users, recentred, rnd.fix_level, strict=True):
                reports[name].recentred += int(flag)
                self._users[name].pin()
                self.floor_stage.start(name, level)
            self._follow_floors(rnd.fix_users)

    def _carry(self, rides: list[tuple[str, float]]) -> None:
        """Escalator rides: the escalator carried each user, standing, ``rise / tan(incline)`` along the way
        they faced (the last step's heading); the phone counted no step for it (beyond both papers)."""
        rides = [(n, r) for n, r in rides if math.isfinite(self._users[n].heading)]
        if not rides:
            return
        slots = np.array([self._users[n].slot for n, _ in rides], dtype=np.int64)
        incline = math.tan(math.radians(self.params.floors.escalator_incline_deg))
        lengths = np.array([abs(r) / incline for _, r in rides])
        headings = np.array([self._users[n].heading for n, _ in rides])
        self.filters.step(slots, np.arange(len(rides) + 1, dtype=np.int64), lengths, headings)

    def _observe_stretches(self, rnd: Round) -> None:
        """The straight stretches this round's steps completed, each weighed against the floor plan's grid
        (``DynamicSlam.observe_heading_axis``): a user's k-th stretch of the round in the k-th tracker call,
        since a call takes each user once."""
        table = self._stretches
        done = [
            table.add(name, np.asarray(ls), np.asarray(hs))
            for name, ls, hs in zip(rnd.users, rnd.step_len, rnd.step_head, strict=True)
        ]
        for k in range(max((len(d) for d in done), default=0)):
            who = [i for i, d in enumerate(done) if len(d) > k]
            slots = np.array([self._users[rnd.users[i]].slot for i in who], dtype=np.int64)
            self.filters.observe_heading_axis(slots, np.array([done[i][k] for i in who]))

    def _revise_headings(self, users: list[UserTrack]) -> None:
        """Beyond both papers: the PDR front-end sends each step with its current estimate of the north
        offset of its gyroscope yaw (``slam_core.sensing.pdr.heading``), an estimate that improves as the walk
        goes on. The path dead-reckoned since the user's last absolute observation is then due the same turn
        the tracker's plain dead reckoning makes; its particles are translated by that revision (the cloud
        keeps its shape: each particle's own bias and scale still apply on top)."""
        slots, shifts = [], []
        for u in users:
            shift = u.revision()
            if float(np.hypot(*shift)) > 1e-9:
                slots.append(u.slot)
                shifts.append(shift)
        if slots:
            self.filters.shift(np.array(slots, dtype=np.int64), np.array(shifts))

    def _add_to_graph(self, names: list[str], ids: list[int], changed: set[int]) -> None:
        changed.update(ids)
        if self.params.crowd_solver == "graph":
            for name, c in zip(names, ids, strict=True):
                u = self._users[name]
                self.graph.add_detection(u.number, int(c), u.displacement, u.walked)

    def _offer_crowd_map(self) -> None:
        for users, level in self._by_level(self.filters.active_users):
            self.filters.merge_crowd_map(users, self.crowd.snapshot(level))

    def _rows(self, users: list[str]) -> dict[str, EstimateRow]:
        if not users:
            return {}
        summary = self.filters.summaries(np.array([self._users[n].slot for n in users], dtype=np.int64))
        if self.floor_stage.single:
            return {  # rows as Python floats at once: indexing each numpy row cost more than the row
                n: EstimateRow(self._users[n].last_t_ms, x, y, (xx, xy, yy), (bx, by), heading)
                for n, (x, y, xx, xy, yy, bx, by, heading) in zip(users, summary.tolist(), strict=True)
            }
        floors = self.floor_stage.believed_of(users)
        return {
            n: EstimateRow(self._users[n].last_t_ms, x, y, (xx, xy, yy), (bx, by), heading, level, p)
            for n, (x, y, xx, xy, yy, bx, by, heading), (level, p) in zip(
                users, summary.tolist(), floors, strict=True
            )
        }


def _with_detections(b: UserBatch, events: AnchorEvents) -> dict[str, Any]:
    """The batch's detection fields with the front-end's ``events`` after the phone's own."""
    if not events.t_ms.size:
        return {}
    signatures = b.detect_signature or ("",) * b.detect_t.size
    observed = b.detect_observed_t if b.detect_observed_t.size else b.detect_t
    rises = b.detect_rise if b.detect_rise.size else np.full(b.detect_t.size, math.nan)
    return {
        "detect_t": np.concatenate([b.detect_t, events.t_ms]),
        "detect_type": np.concatenate([b.detect_type, events.type_index]),
        "detect_signature": signatures + events.signature,
        "detect_observed_t": np.concatenate([observed, events.observed_t_ms]),
        "detect_rise": np.concatenate([rises, events.rise_m]),
    }


def _latest_time(b: UserBatch) -> int:
    """The latest time anywhere in a batch, raw IMU included (-1: nothing timed)."""
    latest = _heard_until(b)
    if b.imu is not None:
        for stream in (b.imu.acc, b.imu.gyr, b.imu.mag):
            if stream is not None and stream.size:
                latest = max(latest, int(stream[:, 0].max()))
    return latest


def _heard_until(b: UserBatch) -> int:
    """The latest time a batch reports anything at (-1: nothing timed)."""
    latest = -1
    for times in (b.fix_t, b.step_t, b.detect_t, b.scan_t, b.peer_t, b.beacon_t):
        if times.size:  # a list's max: numpy's costs more than these few numbers
            latest = max(latest, max(times.tolist()))
    return int(latest)
