"""Crowd replay of a floor, or a whole building, of Indoor Location 2.0 walks through the server's own batch
path.

Every walk becomes a concurrent user (all start at the same replay time): its trace is cut into the
one-second sensor batches a phone would post (``msindoor_batches``), converted by
``server.ingestion.convert`` and applied with ``BuildingTracker.apply``, one call per replay second for every
walk that has data, as the server's per-building worker does. Each walk starts from its first waypoint as a
position fix (heading from the phone); its position is scored at every later waypoint. Windows are also cut at
waypoint times, so the scored estimate is the one the server held at the waypoint's time, never one informed
by later sensor data.

With ``warm_split`` the earlier walks (by recorded start time) are replayed first as a crowd of their own
and build the building's shared map; only the later walks, replayed afterwards, are scored. With
``warm_pick`` "alternate" every other walk warms the crowd instead: a building walked everywhere.

A building's folder (its floors as subfolders, ``msindoor.building_floors``) is replayed as one crowd in one
building, each floor with its plan and each walk's fix naming its floor; the warm split takes each floor's
earliest walks (the data set's floors were walked on different days: a split over the building by time would
leave some floors without a crowd), so the building scores the walks its floors score one by one. Each scored
waypoint also scores the floor the server believed the user on.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from schemas.common import Position
from schemas.sensors import PositionFix
from server.datasets.msindoor import (
    PlanReading,
    Trace,
    WifiScan,
    building_floors,
    iter_windows,
    read_floor,
    read_floor_plan,
    read_trace,
    shifted,
    shop_frontages,
)
from server.datasets.msindoor_batches import trace_windows
from server.ingestion.convert import BuildingContext, building_context, to_user_batch
from server.ingestion.floor_plans import engine_plan
from server.ingestion.radio_maps import RadioMap
from server.slam.config import ReplayOptions, replay_params
from slam_core.crowd.fingerprints import NOBODY
from slam_core.encounters.models import Calibration
from slam_core.filter.floor_plan import PlanIndex
from slam_core.sim.simulation import FRONTAGE_M
from slam_core.sim.statistics import error_summary
from slam_core.tracking.fingerprint_stage import FingerprintStage
from slam_core.tracking.floors import Floors
from slam_core.tracking.tracker import BuildingTracker, TrackerParams, UserBatch
from slam_core.wifi.pairs import fresh_mask
from slam_core.zones.visits import ZoneTally

REPLAY_BASE_MS = 1_700_000_000_000
"""Replay time of every walk's first sample (a valid wire timestamp)."""
PHASE_GAP_MS = 60_000
"""Between the warm-up crowd's last sample and the scored crowd's first."""
START_SIGMA_M = 1.0
"""A surveyed waypoint is a surveyor's click: about a metre (a walk's start fix, a tagged walk's ends)."""
FLOOR_PENALTY_M = 15.0
"""The competition's score: mean metres of error plus this many per floor of error."""
FLOOR_BY_MS = 10_000
"""Without a start fix: is a walk on the right floor by its 10th second, and after."""


@dataclass
class _Walk:
    name: str
    trace: Trace
    waypoints: np.ndarray  # (K, 3) t, x, y in replay time
    level: int = 0  # the floor it was walked on
    start_ms: int = 0  # its first sample, in replay time
    pending: int = 1  # the next waypoint to score (the first is the start fix; without one, it is scored)
    errors: list[float] = field(default_factory=list)
    floor_errors: list[int] = field(default_factory=list)
    """Per entry of ``errors``: how many floors off the server's floor was."""
    floor_seen: list[tuple[float, bool]] = field(default_factory=list)
    """(time since the walk's first sample in ms, right floor) after every call that estimated it."""
    belief_seen: list[tuple[float, bool]] = field(default_factory=list)
    """... after every call, whether the server's most probable floor was the right one, placed or not (a
    phone being placed has a floor before it has a position it is told)."""
    scored: list[tuple[float, float]] = field(default_factory=list)
    """(time, error) of every scored waypoint, inf while the user had no reported position."""

    def seconds_to(self, metres: float) -> float:
        """Walking time from the first scored waypoint until the error stays within ``metres`` (inf if it
        never does)."""
        if not self.scored:
            return math.inf
        times = np.array([t for t, _ in self.scored])
        errors = np.array([e for _, e in self.scored])
        above = np.flatnonzero(errors > metres)
        if above.size == 0:
            return 0.0
        if above[-1] == errors.size - 1:
            return math.inf
        return float(times[above[-1] + 1] - times[0]) / 1000.0

    before: tuple[np.ndarray, np.ndarray] | None = None  # the estimate and displacement after the last call

    def truth(self, t_ms: float) -> np.ndarray | None:
        """The surveyed position at ``t_ms`` (``_surveyed_at``)."""
        return _surveyed_at(self.waypoints, t_ms)


def _surveyed_at(waypoints: np.ndarray, t_ms: float) -> np.ndarray | None:
    """The surveyed position at ``t_ms`` (straight between clicks), inside the surveyed span only."""
    w = waypoints
    if not w[0, 0] <= t_ms <= w[-1, 0]:
        return None
    return np.array([np.interp(t_ms, w[:, 0], w[:, 1]), np.interp(t_ms, w[:, 0], w[:, 2])])


def _first_sample_ms(trace: Trace) -> float:
    """The time of the walk's first sensor sample: where its replay, and its first 10 s, begin."""
    return min(float(s[0, 0]) for s in trace.streams.values() if len(s))


CORRECTIONS = ("building_anchor", "signature_anchor", "human_anchor", "fingerprint_fix", "none")
"""What moved a user in a call, beyond its steps (``none``: steps alone, with the floor plan's weights)."""


@dataclass
class _Audit:
    """Per kind of correction: calls that applied it, those after which the user was farther from the
    surveyed track than its steps alone would have left it, and the sum of that change (metres)."""

    applied: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CORRECTIONS, 0))
    away: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CORRECTIONS, 0))
    change_m: dict[str, float] = field(default_factory=lambda: dict.fromkeys(CORRECTIONS, 0.0))
    fix_errors: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, dict[str, float | int]]:
        return {
            kind: {
                "applied": self.applied[kind],
                "moved_away_share": self.away[kind] / self.applied[kind] if self.applied[kind] else 0.0,
                "mean_error_change_m": self.change_m[kind] / self.applied[kind]
                if self.applied[kind]
                else 0.0,
            }
            for kind in CORRECTIONS
        }


def replay_msindoor(
    floor_dir: Path,
    options: ReplayOptions,
    base_params: TrackerParams,
    calibration: Calibration,
    progress: Callable[[int, int], None] | None = None,
    radio_map_of: Callable[[list[Trace], BuildingContext], RadioMap | None] | None = None,
) -> tuple[dict[str, Any], np.ndarray]:
    """Replay the floor's (or the building's) walks with the server's tracker (``base_params``, in the
    options' mode); returns the metrics (the simulated evaluation's fields plus ``n_waypoints``, and for a
    building also per floor) and every scored waypoint's error in metres. With a warm split and
    ``radio_map_of`` (``server.signal_maps.tagged_walks``), the warm walks are built into a radio map, as a
    server's signal-map build, which the tracker loads before the scored walks (a floor only)."""
    started = time.perf_counter()
    floors = building_floors(floor_dir)
    tracker = BuildingTracker(replay_params(base_params, options), calibration, seed=options.tracker_seed)
    tracker.set_levels(tuple(level for level, _ in floors))
    warm: list[tuple[int, Trace]] = []
    later: list[tuple[int, Trace]] = []
    readings: dict[int, tuple[PlanReading, PlanIndex | None, list[Trace]]] = {}
    zones: list[tuple[str, np.ndarray, int]] = []
    for level, folder in floors:
        floor = read_floor(folder)
        found = [read_trace(p) for p in floor.traces]
        found = [t for t in found if len(t.waypoints) >= 2 and len(t.streams.get("accelerometer", ()))]
        found.sort(key=lambda t: (t.start_ms, t.path.name))
        picks = options.warm_walks(len(found))
        warm += [(level, t) for t, pick in zip(found, picks, strict=True) if pick]
        later += [(level, t) for t, pick in zip(found, picks, strict=True) if not pick]
        if options.floor_plan:
            reading = read_floor_plan(floor)
            index = None if reading.plan is None else engine_plan(reading.plan)
            tracker.set_floor_plan(index, level)
            readings[level] = (reading, index, found)
        if options.zones:
            plan = (readings[level][0] if level in readings else read_floor_plan(floor)).plan
            for name, ring in shop_frontages(plan, FRONTAGE_M) if plan is not None else []:
                zones.append((f"{level}/{len(zones)} {name}", ring, level))
    tally = None
    if zones:
        ids = [z[0] for z in zones]
        tracker.zones.set_zones(ids, [z[1] for z in zones], [z[2] for z in zones], [None] * len(zones))
        tally = ZoneTally(tracker.zones.zones, ids)
    traces = [t for _, t in warm + later]
    if not traces:
        raise ValueError(f"{floor_dir}: no walk has an accelerometer stream and two waypoints")
    phases = [warm, later] if warm else [later]
    single = len(floors) == 1
    ctx = building_context(floor_dir.name, tracker, {}, None, None)
    base = REPLAY_BASE_MS
    scored: list[_Walk] = []
    counts = dict.fromkeys(
        (
            "steps",
            "encounter_detections",
            "encounters",
            "encounters_applied",
            "signatures_applied",
            "signatures_gated",
            "fingerprint_fixes",
        ),
        0,
    )
    total_windows = sum(_windows(t, options.window_ms) for t in traces)
    audit = _Audit()
    radio_scans = 0

    def advance(n: int) -> None:
        _tick(progress, n, total_windows)

    for phase, phase_traces in enumerate(phases):
        last = phase == len(phases) - 1
        start_fix = options.start_fix or not last  # the warm crowd always starts at its first waypoint
        walks = [_prepare(t, base, start_fix, level) for level, t in phase_traces]
        audited = audit if last else _Audit()  # the scored walks only
        end = _replay_phase(
            tracker, walks, ctx, options, counts, advance, audited, start_fix, tally if last else None
        )
        if last:
            scored = walks
        elif radio_map_of is not None and single:
            radio = radio_map_of([t for _, t in phase_traces], ctx)
            if radio is not None:
                radio_scans = tracker.load_radio_map(
                    radio.map_id, radio.xy, radio.bssids, radio.rss, radio.t_ms
                )
        base = end + PHASE_GAP_MS
    errors = np.array([e for w in scored for e in w.errors])
    reach = (
        np.concatenate(
            [
                _start_reach([t for lv, t in warm if lv == level], [t for lv, t in later if lv == level])
                for level, _ in floors
                if any(lv == level for lv, _ in warm) and any(lv == level for lv, _ in later)
            ]
            or [np.zeros(0)]
        )
        if len(phases) == 2
        else None
    )
    plan_readings = {
        level: _plan_reading(reading, index, found) for level, (reading, index, found) in readings.items()
    }
    result: dict[str, Any] = {
        "mode": options.mode,
        "floor": str(floor_dir),
        "levels": [level for level, _ in floors],
        "seed": options.seed,
        "sampling": options.sampling,
        "particles": options.particles,
        "motion_model": options.motion_model,
        "crowd_solver": options.crowd_solver,
        "warm_split": options.warm_split,
        "warm_pick": options.warm_pick if options.warms else None,
        "floor_plan": any(index is not None for _, index, _ in readings.values()),
        "floor_plan_reading": (plan_readings.get(floors[0][0]) if single else plan_readings) or None,
        "heading_axes": any(index is not None for _, index, _ in readings.values()) and options.heading_axes,
        "start_fix": options.start_fix,
        "unplaced_waypoints": sum(1 for w in scored for _, e in w.scored if not math.isfinite(e)),
        "seconds_to_5m": _median_or_none([w.seconds_to(5.0) for w in scored]),
        "walks_within_5m": sum(math.isfinite(w.seconds_to(5.0)) for w in scored) / max(1, len(scored)),
        "start_to_warm_track_m": None if reach is None or not reach.size else error_summary(reach),
        "oracle_walks_right_floor_by_10s": None
        if len(phases) < 2 or single
        else _floor_oracle(warm, later, tracker.params),
        "starts_within_5m_of_warm_track": None
        if reach is None or not reach.size
        else float(np.mean(reach <= 5.0)),
        **error_summary(errors),
        **_floor_scores(scored),
        "per_floor": None
        if single
        else {
            str(level): {
                **_summary_or_none(np.array([e for w in scored if w.level == level for e in w.errors])),
                **_floor_scores([w for w in scored if w.level == level]),
                "n_scored_walks": sum(w.level == level for w in scored),
                "n_waypoints": sum(len(w.errors) for w in scored if w.level == level),
            }
            for level, _ in floors
            if any(w.level == level for w in scored)
        },
        "n_waypoints": int(errors.size),
        "n_walks": len(traces),
        "n_scored_walks": len(scored),
        "steps_detected": counts["steps"],
        "encounter_detections_per_user": 2 * counts["encounter_detections"] / len(traces),
        "encounters_per_user": 2 * counts["encounters"] / len(traces),
        "encounters_applied_per_user": 2 * counts["encounters_applied"] / len(traces),
        "crowd_anchors": len(tracker.crowd),
        "detections_per_walk": {k: v / len(traces) for k, v in tracker.front_end.fired.items()},
        "signature_observations_applied": counts["signatures_applied"],
        "signature_observations_gated": counts["signatures_gated"],
        "fingerprints": tracker.params.fingerprints.enabled,
        "fingerprint_fixes": counts["fingerprint_fixes"],
        "fingerprint_fix_error_m": error_summary(np.array(audit.fix_errors)) if audit.fix_errors else None,
        "corrections": audit.summary(),
        "radio_map_scans": radio_scans,
    }
    if tally is not None:
        result["zones"] = tally.result()
    result["seconds"] = time.perf_counter() - started
    return result, errors


def floors_alone(
    building_dir: Path,
    result: dict[str, Any],
    options: ReplayOptions,
    base_params: TrackerParams,
    calibration: Calibration,
    progress: Callable[[str], Callable[[int, int], None] | None] | None = None,
) -> dict[str, dict[str, Any]]:
    """Each floor of a building replayed alone with the same options, beside its figures in the building's
    replay (``result``): by level, both medians and p90s and the building's over the floor's alone. A floor
    should do no worse among the others (the same walks, warmed and scored alike) than alone, but for the
    filters' seed noise. ``progress`` gives a floor's progress callback by its folder's name."""
    per_floor = result.get("per_floor")
    if per_floor is None:
        raise ValueError(f"{building_dir}: a floor, not a building of floors; nothing to compare it with")
    out: dict[str, dict[str, Any]] = {}
    for level, folder in building_floors(building_dir):
        inside = per_floor.get(str(level))
        if inside is None or inside["median_m"] is None:
            continue
        alone, _ = replay_msindoor(
            folder, options, base_params, calibration, progress(folder.name) if progress else None
        )
        out[str(level)] = {
            "floor": folder.name,
            "median_m": inside["median_m"],
            "p90_m": inside["p90_m"],
            "alone_median_m": alone["median_m"],
            "alone_p90_m": alone["p90_m"],
            "median_vs_alone": inside["median_m"] / alone["median_m"],
            "p90_vs_alone": inside["p90_m"] / alone["p90_m"],
        }
    return out


def _summary_or_none(errors: np.ndarray) -> dict[str, Any]:
    """``error_summary``, or its keys with None when a floor had no scored waypoint with a position."""
    if errors.size:
        return dict(error_summary(errors))
    return dict.fromkeys(error_summary(np.zeros(1)), None)


def _floor_scores(walks: list[_Walk]) -> dict[str, Any]:
    """The floor figures of these scored walks: the share of scored estimates on the right floor, the
    competition's score (mean metres + 15 x mean floors off), and the share of walks on the right floor by
    their 10th second and of their estimates after it."""
    errors = [e for w in walks for e in w.errors]
    floors_off = [f for w in walks for f in w.floor_errors]
    # a walk the server had not placed by its 10th second was on no floor the phone was told of
    by_10 = [_right_by_10s(w.floor_seen) for w in walks]
    believed_by_10 = [_right_by_10s(w.belief_seen) for w in walks]
    after = [right for w in walks for t, right in w.floor_seen if t > FLOOR_BY_MS]
    return {
        "right_floor": float(np.mean([f == 0 for f in floors_off])) if floors_off else None,
        "competition_score": float(np.mean(errors) + FLOOR_PENALTY_M * np.mean(floors_off))
        if errors
        else None,
        "walks_right_floor_by_10s": float(np.mean(by_10)) if by_10 else None,
        "walks_believed_right_floor_by_10s": float(np.mean(believed_by_10)) if believed_by_10 else None,
        "right_floor_after_10s": float(np.mean(after)) if after else None,
    }


def _right_by_10s(seen: list[tuple[float, bool]]) -> bool:
    """Whether the last floor seen by the walk's 10th second was the right one (False: none seen by then)."""
    return next((right for t, right in reversed(seen) if t <= FLOOR_BY_MS), False)


def _plan_reading(reading: PlanReading, index: PlanIndex | None, traces: list[Trace]) -> dict[str, Any]:
    """What of the floor's map the plan left out, and the share of every walk's surveyed waypoints inside
    its walkable area: a plan that does not line up with the floor shows here before it misleads a filter."""
    waypoints = np.concatenate([t.waypoints[:, 1:3] for t in traces])
    return {
        "skipped_features": reading.skipped_features,
        "repaired_rings": reading.repaired_rings,
        "dropped_rings": reading.dropped_rings,
        "waypoints_walkable": None if index is None else float(np.mean(index.walkable(waypoints))),
    }


def _start_reach(warm: list[Trace], scored: list[Trace]) -> np.ndarray:
    """How far each scored walk's first waypoint lies from every warm walk's surveyed track (straight between
    clicks), in metres: what bounds a phone placed without a fix, which the crowd's map can only put where the
    warm crowd has been."""
    segments = np.concatenate([np.hstack([t.waypoints[:-1, 1:3], t.waypoints[1:, 1:3]]) for t in warm])
    a, d = segments[:, :2], segments[:, 2:] - segments[:, :2]
    length2 = np.maximum((d * d).sum(axis=1), 1e-12)
    out = np.empty(len(scored))
    for k, trace in enumerate(scored):
        p = trace.waypoints[0, 1:3]
        t = np.clip(((p - a) * d).sum(axis=1) / length2, 0.0, 1.0)
        out[k] = float(np.min(np.hypot(*(a + t[:, None] * d - p).T)))
    return out


def _floor_oracle(
    warm: list[tuple[int, Trace]],
    scored: list[tuple[int, Trace]],
    params: TrackerParams,
) -> float:
    """The share of scored walks put on their floor by their first ``FLOOR_BY_MS`` of scans, as the
    tracker weighs a phone not yet placed (``FingerprintStage.floor_evidence`` anywhere on each floor,
    ``Floors.weigh`` from a uniform belief), but on a perfect crowd's maps: the warm walks' scans at their
    surveyed positions and floors (a radio map). What bounds a cold phone's floor from its radio alone; a
    walk with no scan that tells two floors apart by then is on none."""
    levels = tuple(sorted({level for level, _ in warm} | {level for level, _ in scored}))
    stage = FingerprintStage(
        replace(params.fingerprints, enabled=True), params.detection.stale_ap_ms, params.floors
    )
    floors = Floors(params.floors, levels)
    xy, bssids, rss, times, on = [], [], [], [], []
    for level, trace in warm:
        for scan in trace.wifi:
            at = _surveyed_at(trace.waypoints, scan.t_ms)
            if at is not None:
                heard, heard_rss = _fresh_entries(scan, stage.stale_ap_ms)
                xy.append(at)
                bssids.append(heard)
                rss.append(heard_rss)
                times.append(scan.t_ms)
                on.append(level)
    stage.load_radio_map("oracle", np.array(xy), bssids, rss, np.array(times), np.array(on))
    right = []
    for level, trace in scored:
        first = _first_sample_ms(trace)
        belief, informed = floors.uniform(), False
        for scan in trace.wifi:
            if scan.t_ms - first > FLOOR_BY_MS:
                break
            heard, heard_rss = _fresh_entries(scan, stage.stale_ap_ms)
            evidence = stage.floor_evidence(levels, NOBODY, heard, heard_rss, None)
            informed |= int(np.isfinite(evidence).sum()) >= 2
            belief = floors.weigh(belief, evidence)
        right.append(informed and floors.believed(belief)[0] == level)
    return float(np.mean(right)) if right else math.nan


def _fresh_entries(scan: WifiScan, stale_ms: int) -> tuple[list[str], np.ndarray]:
    """A scan's BSSIDs and RSS heard within ``stale_ms`` of it (``fresh_mask``), as a phone's batch keeps."""
    fresh = fresh_mask(scan.t_ms, scan.last_seen_ms, stale_ms)
    return [b for b, f in zip(scan.bssid, fresh, strict=True) if f], scan.rssi_dbm[fresh]


def _windows(trace: Trace, window_ms: int) -> int:
    """How many batch windows the replay cuts the walk into (an upper bound: empty ones are skipped)."""
    return sum(1 for _ in iter_windows(trace, window_ms, trace.waypoints[:, 0].astype(np.int64).tolist()))


def _tick(progress: Callable[[int, int], None] | None, n: int, total: int) -> None:
    if progress is not None:
        progress(n, total)


def _prepare(trace: Trace, base_ms: int, start_fix: bool, level: int = 0) -> _Walk:
    moved = shifted(trace, base_ms - int(_first_sample_ms(trace)))
    return _Walk(trace.path.stem, moved, moved.waypoints, level, base_ms, pending=1 if start_fix else 0)


def _replay_phase(
    tracker: BuildingTracker,
    walks: list[_Walk],
    ctx: BuildingContext,
    options: ReplayOptions,
    counts: dict[str, int],
    advance: Callable[[int], None],
    audit: _Audit,
    start_fix: bool = True,
    tally: ZoneTally | None = None,
) -> int:
    """Replay these walks concurrently, each started by a fix at its first waypoint unless ``start_fix`` is
    off; returns the replay time of the last window's end."""
    queue: list[tuple[int, int, UserBatch]] = []
    for index, walk in enumerate(walks):
        start_t = int(walk.waypoints[0, 0])
        fixed = not start_fix
        cuts = walk.waypoints[:, 0].astype(np.int64).tolist()
        for end, batch in trace_windows(walk.trace, ctx.building_id, walk.name, options.window_ms, cuts=cuts):
            if not fixed and end > start_t:
                fix = PositionFix(
                    t_ms=start_t,
                    position=Position(x_m=float(walk.waypoints[0, 1]), y_m=float(walk.waypoints[0, 2])),
                    sigma_m=START_SIGMA_M,
                    floor=walk.level,
                )
                batch = batch.model_copy(update={"landmarks": [*batch.landmarks, fix]})
                fixed = True
            queue.append((end, index, to_user_batch(batch, ctx).user_batch))
    queue.sort(key=lambda item: (item[0], item[1]))
    last_end = REPLAY_BASE_MS
    call: list[tuple[int, int, UserBatch]] = []
    call_end = -1
    for item in queue:
        end, index, _ = item
        if call and (end > call_end or any(i == index for _, i, _ in call)):
            _apply(tracker, walks, call, options, counts, audit, tally)
            advance(len(call))
            call = []
        if not call:
            call_end = end + (-(end - REPLAY_BASE_MS) % options.window_ms)
        call.append(item)
        last_end = max(last_end, end)
    if call:
        _apply(tracker, walks, call, options, counts, audit, tally)
        advance(len(call))
    for walk in walks:  # waypoints after the walk's last sample: its final estimate
        _score(tracker, walk, math.inf, options.mode)
    return last_end


def _apply(
    tracker: BuildingTracker,
    walks: list[_Walk],
    call: list[tuple[int, int, UserBatch]],
    options: ReplayOptions,
    counts: dict[str, int],
    audit: _Audit,
    tally: ZoneTally | None = None,
) -> None:
    outcome = tracker.apply([b for _, _, b in call])
    if tally is not None:
        for e in outcome.zone_events:
            tally.told(e.user, e.zone_id, e.kind, e.t_ms, e.told_ms)
    counts["steps"] += sum(r.steps_detected for r in outcome.reports.values())
    counts["signatures_applied"] += sum(r.signatures_applied for r in outcome.reports.values())
    counts["signatures_gated"] += sum(r.signatures_gated for r in outcome.reports.values())
    counts["fingerprint_fixes"] += sum(r.fingerprint_fixes for r in outcome.reports.values())
    counts["encounter_detections"] += outcome.detections
    counts["encounters"] += len(outcome.encounters)
    counts["encounters_applied"] += sum(e.applied for e in outcome.encounters)
    human = {n for e in outcome.encounters if e.applied for n in (e.detection.user_a, e.detection.user_b)}
    for end, index, batch in call:
        walk = walks[index]
        _score(tracker, walk, end, options.mode)
        level, _ = tracker.floor_of(batch.user)
        walk.belief_seen.append((end - walk.start_ms, level == walk.level))
        if tracker.is_placed(batch.user):
            walk.floor_seen.append((end - walk.start_ms, level == walk.level))
        report = outcome.reports[batch.user]
        truth = walk.truth(end)
        if tally is not None and truth is not None:  # the estimate the phone is told, or none yet
            told = tracker.estimate(batch.user) if tracker.is_placed(batch.user) else None
            xy = np.array([np.nan, np.nan]) if told is None else np.array([told.x, told.y])
            tally.sample(walk.name, end, truth, walk.level, xy, level)
        if report.fingerprint_fix is not None and truth is not None:
            audit.fix_errors.append(float(np.linalg.norm(np.asarray(report.fingerprint_fix) - truth)))
        row, moved = tracker.estimate(batch.user), tracker.displacement(batch.user)
        if row is None or moved is None or report.fixes_applied:  # not started, or (re)started by a fix
            walk.before = None
            continue
        now = np.array([row.x, row.y])
        if walk.before is not None and truth is not None:
            steps_alone = walk.before[0] + (moved - walk.before[1])
            change = float(np.linalg.norm(now - truth) - np.linalg.norm(steps_alone - truth))
            kinds = [
                kind
                for kind, applied in (
                    ("building_anchor", report.detections_applied),
                    ("signature_anchor", report.signatures_applied),
                    ("human_anchor", batch.user in human),
                    ("fingerprint_fix", report.fingerprint_fixes),
                )
                if applied
            ] or ["none"]
            for kind in kinds:
                audit.applied[kind] += 1
                audit.away[kind] += change > 0.0
                audit.change_m[kind] += change
        walk.before = (now, moved)


def _median_or_none(values: list[float]) -> float | None:
    """The median, or None when it is infinite (most walks never got there)."""
    median = float(np.median(values)) if values else math.inf
    return median if math.isfinite(median) else None


def _score(tracker: BuildingTracker, walk: _Walk, until_ms: float, mode: str) -> None:
    """Score the walk's waypoints up to ``until_ms`` with the position the server holds now."""
    while walk.pending < len(walk.waypoints) and walk.waypoints[walk.pending, 0] <= until_ms:
        if mode == "pdr":
            position = tracker.dead_reckoning(walk.name)
        else:  # what the phone is told: nothing while a cold start is not yet placed
            row = tracker.estimate(walk.name) if tracker.is_placed(walk.name) else None
            position = None if row is None else np.array([row.x, row.y])
        error = math.inf
        if position is not None:
            error = float(np.linalg.norm(position - walk.waypoints[walk.pending, 1:]))
            walk.errors.append(error)
            # dead reckoning keeps the floor it started on; the filter says which it believes
            level = walk.level if mode == "pdr" else tracker.floor_of(walk.name)[0]
            walk.floor_errors.append(abs(level - walk.level))
        walk.scored.append((float(walk.waypoints[walk.pending, 0]), error))
        walk.pending += 1
