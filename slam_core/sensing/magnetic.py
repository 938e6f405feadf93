"""Magnetic anomalies as organic building anchors (SemanticSLAM's magnetic landmarks; DynamicSLAM's
``magnetic`` type), from the magnetometer's magnitude, which does not depend on how the phone is held.

The magnitude is smoothed over ``smoothing_s`` and compared with the user's own slowly moving baseline (the
undisturbed field where the user walks, ``baseline_s``). An anomaly is a stretch where they differ by at
least ``anomaly_ut``; it is reported once, as soon as the deviation has fallen ``peak_drop_ut`` from its
peak, with the peak's time as the moment the user was at the anchor. Anomalies carry no identity: the
engine associates them by type and position (Eq. 15-16), as it does turns.

Off by default. On the msindoor mall floor the field swings between 32 and 76 uT along the corridors, so
anomalies are many and alike: profiles of peaks (+-2 s of magnitude) from different walks that agree
(RMS < 5 uT, correlation > 0.7) lie within 5 m of each other in 13 % of pairs within 30 m, against 10 % for
any pair: their shape does not tell them apart, and placed by position they behave like the turns.
Per user, sample by sample with carried state. Pure numerics: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MagneticParams:
    enabled: bool = False
    smoothing_s: float = 0.5
    baseline_s: float = 20.0
    anomaly_ut: float = 12.0
    """Deviation from the baseline that makes an anomaly (the earth's field is 25-65 uT; steel and cables
    indoors add tens of uT within a metre or two)."""
    peak_drop_ut: float = 4.0
    max_anomaly_ms: float = 8_000.0
    """A deviation that lasts longer is a new level of the field, not a local anomaly: the baseline jumps
    to it (and an anomaly not yet reported is dropped)."""
    max_gap_ms: float = 1_000.0
    type_index: int = 4  # the engine's "magnetic"

    def __post_init__(self) -> None:
        if not (
            0.0 < self.smoothing_s < self.baseline_s
            and 0.0 < self.peak_drop_ut < self.anomaly_ut
            and self.max_gap_ms > 0.0
            and self.max_anomaly_ms > 0.0
        ):
            raise ValueError(
                "need 0 < smoothing_s < baseline_s, 0 < peak_drop_ut < anomaly_ut, max_gap_ms > 0"
            )


@dataclass
class MagneticState:
    last_t: float = math.nan
    field: float = math.nan  # smoothed magnitude, uT
    baseline: float = math.nan
    in_anomaly: bool = False
    reported: bool = False
    peak: float = 0.0  # |deviation| at the peak
    peak_t: float = math.nan
    start_t: float = math.nan


def detect_magnetic_anomalies(
    state: MagneticState, params: MagneticParams, mag: np.ndarray
) -> list[tuple[int, int]]:
    """Feed one batch of magnetometer rows (t_ms, x, y, z in uT; times strictly increasing, also across
    batches). Returns (report time, peak time) of each anomaly that became known in it."""
    mag = np.asarray(mag, dtype=float).reshape(-1, 4)
    if not np.all(np.isfinite(mag)):
        raise ValueError("mag: samples must be finite")
    if mag.shape[0] > 1 and np.any(np.diff(mag[:, 0]) <= 0):
        raise ValueError("mag: sample times must strictly increase")
    if mag.size and not math.isnan(state.last_t) and mag[0, 0] <= state.last_t:
        raise ValueError("mag: sample times must strictly increase, also across batches")
    out: list[tuple[int, int]] = []
    p = params
    for t, magnitude in zip(mag[:, 0], np.linalg.norm(mag[:, 1:4], axis=1), strict=True):
        dt = t - state.last_t if not math.isnan(state.last_t) else math.inf
        state.last_t = float(t)
        if dt > p.max_gap_ms:
            state.field = state.baseline = float(magnitude)
            state.in_anomaly = False
            continue
        state.field += (1.0 - math.exp(-dt / (p.smoothing_s * 1e3))) * (magnitude - state.field)
        deviation = abs(state.field - state.baseline)
        if not state.in_anomaly:
            # the baseline learns only undisturbed field, so an anomaly does not drag it along
            state.baseline += (1.0 - math.exp(-dt / (p.baseline_s * 1e3))) * (state.field - state.baseline)
            if deviation >= p.anomaly_ut:
                state.in_anomaly, state.reported = True, False
                state.peak, state.peak_t, state.start_t = deviation, float(t), float(t)
            continue
        if t - state.start_t > p.max_anomaly_ms:
            state.baseline = state.field
            state.in_anomaly = False
            continue
        if deviation > state.peak and not state.reported:
            state.peak, state.peak_t = deviation, float(t)
        if not state.reported and deviation <= state.peak - p.peak_drop_ut:
            state.reported = True
            out.append((int(t), int(state.peak_t)))
        if deviation < p.anomaly_ut / 2.0:
            state.in_anomaly = False
    return out
