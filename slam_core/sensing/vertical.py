"""Changes of floor from the barometer: elevators, stairs and escalators as typed building anchors.

Beyond both papers' detectors (SemanticSLAM and DynamicSLAM take elevators and stairs from the
accelerometer's vertical signature; with a barometer, which most phones carry, the change of height is
measured directly). Pressure becomes height by the standard atmosphere, is smoothed, and a transition is a
departure from the resting height that settles again at least ``floor_change_m`` away. Its kind follows
from how the user moved meanwhile:

- **stairs**: walking (at least ``walking_hz`` steps per second over the transition);
- **elevator**: standing, rising or falling at ``elevator_mps`` or more (lifts run 0.5-2.5 m/s);
- **escalator**: standing, slower (an escalator climbs about 0.25 m/s: 0.5 m/s along a 30 deg incline).

The anchor is where the transition ended (the landing, the lift's door): the event carries that moment as
``observed_t`` and is reported ``settle_ms`` later, when the height has been steady long enough to know the
ride is over. Weather drift (~1 hPa in hours, under a millimetre per second) and door or ventilation
transients (a few tenths of a hPa that come back) stay under the thresholds. Per user, sample by sample with
carried state: a stream in one batch or many gives the same events. Pure numerics: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SEA_LEVEL_HPA = 1013.25


@dataclass(frozen=True)
class VerticalParams:
    enabled: bool = True
    smoothing_s: float = 1.0
    """Time constant of the height's exponential smoothing (a phone barometer's noise is ~0.1-0.3 m)."""
    onset_m: float = 0.6
    """A departure this far from the resting height opens a possible transition."""
    floor_change_m: float = 2.0
    """Smallest settled change that counts as a change of floor (storeys are 2.5-5 m)."""
    settle_m: float = 0.3
    settle_ms: int = 2_000
    """The height stays within ``settle_m`` this long: the transition is over."""
    max_gap_ms: int = 5_000
    """A longer gap between pressure samples restarts the detector (the resting height is unknown)."""
    walking_hz: float = 0.8
    elevator_mps: float = 0.45
    elevator_type: int = 0
    stairs_type: int = 1
    escalator_type: int = 5

    def __post_init__(self) -> None:
        if not (
            self.smoothing_s > 0.0
            and 0.0 < self.settle_m < self.onset_m < self.floor_change_m
            and self.settle_ms > 0
            and self.max_gap_ms > 0
            and self.walking_hz > 0.0
            and self.elevator_mps > 0.0
        ):
            raise ValueError(
                "need smoothing_s > 0, 0 < settle_m < onset_m < floor_change_m, settle_ms, max_gap_ms, "
                "walking_hz and elevator_mps > 0"
            )


@dataclass
class VerticalState:
    last_t: float = math.nan
    height: float = math.nan  # smoothed, metres above the 1013.25 hPa level
    rest: float = math.nan  # the resting height
    moving: bool = False
    start_t: float = math.nan
    start_height: float = math.nan
    settle_t: float = math.nan
    settle_height: float = math.nan
    steps: list[int] = field(default_factory=list)  # recent step times, for the walking rate


@dataclass(frozen=True)
class FloorChange:
    t_ms: int  # when it became known
    observed_t_ms: int  # when the user arrived (the anchor's moment)
    type_index: int
    change_m: float  # signed: up is positive
    duration_ms: int
    steps: int


def pressure_height(hpa: np.ndarray) -> np.ndarray:
    """Standard-atmosphere height (m) of pressures in hPa; only differences matter here."""
    height: np.ndarray = 44_330.77 * (1.0 - (np.asarray(hpa, dtype=float) / SEA_LEVEL_HPA) ** 0.190263)
    return height


def detect_floor_changes(
    state: VerticalState, params: VerticalParams, pressure: np.ndarray, step_t: np.ndarray
) -> list[FloorChange]:
    """Feed one batch: ``pressure`` rows (t_ms, hPa), times strictly increasing also across batches, and the
    times of the steps the user took in it. Returns the transitions completed in this batch; ``state`` is
    updated in place (untouched on bad input)."""
    pressure = np.asarray(pressure, dtype=float).reshape(-1, 2)
    if not np.all(np.isfinite(pressure)):
        raise ValueError("pressure: samples must be finite")
    if pressure.size and not np.all((pressure[:, 1] >= 300.0) & (pressure[:, 1] <= 1100.0)):
        raise ValueError("pressure: values must be air pressures in hPa (300-1100)")
    if pressure.shape[0] > 1 and np.any(np.diff(pressure[:, 0]) <= 0):
        raise ValueError("pressure: sample times must strictly increase")
    if pressure.size and not math.isnan(state.last_t) and pressure[0, 0] <= state.last_t:
        raise ValueError("pressure: sample times must strictly increase, also across batches")
    state.steps.extend(int(t) for t in step_t)
    out: list[FloorChange] = []
    heights = pressure_height(pressure[:, 1])
    for t, h in zip(pressure[:, 0], heights, strict=True):
        _sample(state, params, float(t), float(h), out)
    if pressure.size:  # steps older than any transition still open are no longer needed
        horizon = state.start_t if state.moving else state.last_t
        state.steps = [s for s in state.steps if s >= horizon]
    return out


def _sample(state: VerticalState, p: VerticalParams, t: float, h: float, out: list[FloorChange]) -> None:
    dt = t - state.last_t if not math.isnan(state.last_t) else math.inf
    state.last_t = t
    if dt > p.max_gap_ms:
        state.height = state.rest = h
        state.moving = False
        state.settle_t, state.settle_height = t, h
        return
    state.height += (1.0 - math.exp(-dt / (p.smoothing_s * 1e3))) * (h - state.height)
    if abs(state.height - state.settle_height) > p.settle_m:
        state.settle_t, state.settle_height = t, state.height
    settled = t - state.settle_t >= p.settle_ms
    if not state.moving:
        if abs(state.height - state.rest) > p.onset_m:
            state.moving = True
            state.start_t, state.start_height = t, state.rest
        elif settled:
            state.rest = state.height  # follows the weather while the user stays on a floor
        return
    if not settled:
        return
    state.moving = False
    change = state.height - state.start_height  # steady for settle_ms: the smoothing has caught up
    state.rest = state.height
    if abs(change) < p.floor_change_m:
        return  # a transient (a door, the ventilation) that came back, or less than a storey
    duration = max(state.settle_t - state.start_t, 1.0)
    steps = sum(state.start_t <= s <= state.settle_t for s in state.steps)
    if steps / (duration / 1e3) >= p.walking_hz:
        kind = p.stairs_type
    elif abs(change) / (duration / 1e3) >= p.elevator_mps:
        kind = p.elevator_type
    else:
        kind = p.escalator_type
    # the smoothed height trails a ride at speed v by v tau and enters the settle band tau ln(v tau / band)
    # after the ride ended: the arrival is that much before settle_t
    tau_ms = p.smoothing_s * 1e3
    lag = tau_ms * math.log(max(1.0, abs(change) / duration * tau_ms / p.settle_m))
    arrival = max(state.settle_t - lag, state.start_t)
    out.append(FloorChange(int(t), int(arrival), kind, change, int(duration), steps))
