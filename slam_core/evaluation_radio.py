"""The simulated evaluation's radio stage (``slam_core.evaluation``), as the live tracker's is
(``slam_core.tracker_radio``): a tick's scans localised on the crowd's fingerprint map, and its encounter
detections carried to now through the users' dead reckoning and chosen on the filters' estimates."""

from __future__ import annotations

import numpy as np

from slam_core.crowd_fingerprints import CrowdFingerprints, FingerprintParams, Scan
from slam_core.encounter_detection import MODEL_BLUETOOTH, MODEL_WIFI
from slam_core.encounter_selection import EncounterSelector, pair_key
from slam_core.encounters import Calibration
from slam_core.fastslam import DynamicSlam
from slam_core.simulate import Simulation
from slam_core.simulated_encounters import Encounters
from slam_core.track_placement import carry_variance, guess_variance
from slam_core.tracker_radio import apply_fingerprint_fixes
from slam_core.tracker_rounds import MAX_SPEED_M_PER_MS, VELOCITY_WINDOW_MS, cap_speed


def fingerprint_fixes(
    engine: DynamicSlam,
    fp: CrowdFingerprints,
    params: FingerprintParams,
    sim: Simulation,
    slots: np.ndarray,
    steps_done: np.ndarray,
    dead_reckoned: list[np.ndarray],
    ap_names: list[str],
    scan_user: np.ndarray,
    scan_index: np.ndarray,
) -> int:
    """One tick's scans of the tracked users, through ``slam_core.tracker_radio.apply_fingerprint_fixes`` as
    a tracker call's are (each carried to the user's last applied step, ``steps_done``); returns the fixes
    applied."""
    scans: dict[int, list[Scan]] = {}
    for u, c in zip(scan_user.tolist(), scan_index.tolist(), strict=True):
        if slots[u] < 0:
            continue
        tr = sim.users[u]
        rss = tr.scan_rss[c]
        heard = np.flatnonzero(np.isfinite(rss))
        position = int(np.searchsorted(tr.t, tr.scan_t[c], side="right")) - 1
        shift = dead_reckoned[u][steps_done[u]] - dead_reckoned[u][max(position, 0)]
        t_ms = round(float(tr.scan_t[c]) * 1000.0)
        scans.setdefault(u, []).append(Scan([ap_names[i] for i in heard], rss[heard], shift, t_ms))
    if not scans:
        return 0
    users = sorted(scans)
    summary = engine.summaries(slots[users])
    located = [
        (int(slots[u]), u, row[0:2], np.array([[row[2], row[3]], [row[3], row[4]]]), scans[u])
        for u, row in zip(users, summary, strict=True)
    ]
    return sum(apply_fingerprint_fixes(engine, fp, params, located))


def carried(
    sim: Simulation,
    encounters: Encounters,
    e: np.ndarray,
    dead_reckoned: list[np.ndarray],
    walked_at: list[np.ndarray],
    steps_done: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """For detections ``e`` of this tick, as the tracker places a batch's encounters through its users'
    trails (``slam_core.track_placement.carried_since`` and ``SlotColumns.extrapolated``): user a's
    dead-reckoned displacement from the detection to its last applied step (``steps_done``), or minus its
    guessed walk from that step to a later detection, minus user b's; and the variance of both carries."""
    offset = np.zeros((e.size, 2))
    variance = np.zeros(e.size)
    window_s, max_speed = VELOCITY_WINDOW_MS / 1000.0, MAX_SPEED_M_PER_MS * 1000.0
    for side, users in enumerate((encounters.a[e], encounters.b[e])):
        for k, (u, t) in enumerate(zip(users.tolist(), encounters.t[e].tolist(), strict=True)):
            times, now = sim.users[u].t, int(steps_done[u])
            if t > times[now]:  # after the last step: guessed at the user's recent velocity
                recent = max(int(np.searchsorted(times, times[now] - window_s, side="right")) - 1, 0)
                vx, vy = (dead_reckoned[u][now] - dead_reckoned[u][recent]) / window_s
                ahead = np.array(cap_speed(float(vx), float(vy), max_speed)) * (t - times[now])
                shift = -ahead
                variance[k] += float(guess_variance(ahead))
            else:
                then = max(int(np.searchsorted(times, t, side="right")) - 1, 0)
                shift = dead_reckoned[u][now] - dead_reckoned[u][then]
                variance[k] += float(carry_variance(walked_at[u][now] - walked_at[u][then]))
            offset[k] += shift if side == 0 else -shift
    return offset, variance


def choose(
    engine: DynamicSlam,
    selector: EncounterSelector,
    slots: np.ndarray,
    encounters: Encounters,
    e: np.ndarray,
    calibration: Calibration,
    offset: np.ndarray,
) -> np.ndarray:
    """Mask over detections ``e`` (one tick) of those the selector applies, from the filters' estimates
    (placed at the detections' times by ``offset``, as ``carried`` gives it)."""
    mean_a = engine.summaries(slots[encounters.a[e]])[:, 0:2]
    mean_b = engine.summaries(slots[encounters.b[e]])[:, 0:2]
    predicted = np.hypot(*(mean_a - mean_b - offset).T)
    sigma = np.empty(e.size)
    for code, model in ((MODEL_WIFI, calibration.wifi), (MODEL_BLUETOOTH, calibration.bluetooth)):
        m = encounters.model[e] == code
        sigma[m] = np.sqrt(model.variance_at_distance(predicted[m]))
    keys = [
        pair_key(int(a), int(b), int(c))
        for a, b, c in zip(encounters.a[e], encounters.b[e], encounters.model[e], strict=True)
    ]
    t_ms = np.round(encounters.t[e] * 1000.0).astype(np.int64)
    chosen: np.ndarray = selector.choose(t_ms, keys, predicted, sigma)
    return chosen
