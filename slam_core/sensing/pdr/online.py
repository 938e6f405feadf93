"""Online pedestrian dead reckoning: raw IMU batches in, steps (time, length, direction) out, one user at a
time with all state carried between batches, so a walk posted in one-second batches gives the same steps as
the walk processed whole (tested).

Orientation per accelerometer sample, in order of preference:
1. the phone's rotation vector (held from its latest sample at or before the accelerometer sample): an
   absolute azimuth, north-up, as Android fuses it; else its game rotation vector (no magnetometer: the
   yaw is relative, so the steps carry heading changes);
2. the numba Madgwick filter (``orientation.madgwick_step``) on gyroscope + accelerometer, with the
   magnetometer when sent (absolute azimuth, magnetic north) or without it (yaw relative to the start:
   the steps then carry heading changes, not azimuths);
3. neither: the vertical is taken along the measured acceleration (tilt only) and no direction is known.

With an absolute azimuth and a gyroscope, a step's direction is the gyroscope-integrated yaw referenced to
north by the causal mean of the absolute azimuth (``heading.gyro_heading``); each step also carries that
offset, so a consumer can re-rotate the path already walked when the offset estimate improves.

Steps come from ``steps.detect_steps`` on the earth-vertical acceleration (Weinberg length, circular-mean
direction over the step; the peak that starts a walk after a standstill is not a step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam_core.sensing.pdr.heading import HeadingParams, current_offset, gyro_heading, vertical_rate
from slam_core.sensing.pdr.heading import new_state as new_heading_state
from slam_core.sensing.pdr.orientation import azimuth, madgwick_run, quaternion_from_rotation_vector
from slam_core.sensing.pdr.steps import StepParams, detect_steps, new_state, vertical_acceleration

_NWU_TO_ENU = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
"""+90 deg about up: Madgwick's earth frame is x = magnetic north, z = up (so y = west)."""


@dataclass(frozen=True)
class PdrParams:
    steps: StepParams = field(default_factory=StepParams)
    heading: HeadingParams = field(default_factory=HeadingParams)
    madgwick_gain: float = 0.033
    """ahrs' default gain (Madgwick's beta for a gyroscope error of ~3 deg/s)."""

    def __post_init__(self) -> None:
        if not self.madgwick_gain >= 0.0:
            raise ValueError("madgwick_gain must be >= 0")


@dataclass(frozen=True)
class ImuSamples:
    """One batch of raw sensor streams; each row is (t_ms, x, y, z) and the rotation vector's is
    (t_ms, x, y, z, w) with w NaN when the phone did not send it. Times strictly increase per stream."""

    acc: np.ndarray
    gyr: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    mag: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    rv: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    grv: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    """Game rotation vector, as ``rv``."""
    pressure: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """Barometer (t_ms, hPa): not used by the PDR itself, by the floor-change detector beside it."""

    def __post_init__(self) -> None:
        for name, rows, width in (
            ("acc", self.acc, 4),
            ("gyr", self.gyr, 4),
            ("mag", self.mag, 4),
            ("pressure", self.pressure, 2),
        ):
            _check_stream(name, rows, width)
        for name, rows in (("rv", self.rv), ("grv", self.grv)):
            _check_stream(name, rows, 5)
            if not np.all(np.isfinite(rows[:, :4])):
                raise ValueError(f"{name}: samples must be finite (w may be NaN)")


def _check_stream(name: str, rows: np.ndarray, width: int) -> None:
    if rows.ndim != 2 or rows.shape[1] != width:
        raise ValueError(f"{name}: expected an (N, {width}) array, got shape {rows.shape}")
    if width in (2, 4) and not np.all(np.isfinite(rows)):
        raise ValueError(f"{name}: samples must be finite")
    if rows.shape[0] > 1 and np.any(np.diff(rows[:, 0]) <= 0):
        raise ValueError(f"{name}: sample times must strictly increase")


@dataclass
class PdrState:
    """Everything one user's front-end remembers between batches (pickled with the tracker)."""

    steps: np.ndarray = field(default_factory=new_state)
    heading: np.ndarray = field(default_factory=new_heading_state)
    q: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))  # Madgwick's, NaN until started
    fused_t_ms: float = math.nan
    gyr_hold: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))  # latest (t, x, y, z)
    mag_hold: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    rv_hold: np.ndarray = field(default_factory=lambda: np.full(5, np.nan))
    grv_hold: np.ndarray = field(default_factory=lambda: np.full(5, np.nan))
    last_yaw: float = math.nan  # relative yaw of the previous step (turn mode)


@dataclass(frozen=True)
class PdrSteps:
    t_ms: np.ndarray  # int64
    length_m: np.ndarray
    azimuth_rad: np.ndarray  # clockwise from north; NaN when only the turn is known
    turn_rad: np.ndarray  # counter-clockwise heading change since the previous step; NaN with an azimuth
    heading_offset_rad: np.ndarray
    """The part of each azimuth that references the gyroscope-integrated yaw to north (azimuth minus
    offset is the relative yaw); NaN when the azimuth is the absolute one as measured."""


def _held(samples: np.ndarray, hold: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each time's latest sample at or before it (zero-order hold, the previous batch's last sample before
    this batch's first); rows of NaN where none exists. Returns the values and the new hold."""
    rows = np.vstack([hold[None, :], samples]) if samples.size else hold[None, :]
    if samples.size and math.isnan(hold[0]):
        rows = samples
    index = np.searchsorted(rows[:, 0], t, side="right") - 1
    values = np.where((index >= 0)[:, None], rows[np.maximum(index, 0), 1:], np.nan)
    return values, rows[-1].copy()


def _tilt_quaternion(acc: np.ndarray) -> np.ndarray:
    """The quaternion that levels one accelerometer sample (roll and pitch only, yaw zero), as ``ahrs``'
    ``acc2q`` initialises Madgwick."""
    ax, ay, az = acc / max(float(np.linalg.norm(acc)), 1e-9)
    roll, pitch = math.atan2(ay, az), math.atan2(-ax, math.sqrt(ay * ay + az * az))
    cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    return np.array([cr * cp, sr * cp, cr * sp, -sr * sp])


def _start_quaternion(acc: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """Madgwick's starting attitude: levelled by gravity and, with a magnetometer sample, turned so the
    horizontal field points along the earth x axis (``ahrs``' ``am2q``); a cold start at yaw zero would
    take Madgwick's small gain half a minute to swing round."""
    q = _tilt_quaternion(acc)
    if not np.all(np.isfinite(mag)) or not np.any(mag):
        return q
    w, x, y, z = q
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    levelled = rotation @ mag
    yaw = math.atan2(levelled[1], levelled[0])
    turn = np.array([math.cos(-yaw / 2), 0.0, 0.0, math.sin(-yaw / 2)])
    started: np.ndarray = _multiply(turn, q[None, :])[0]
    return started


def _multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    pw, px, py, pz = p
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def _orientation(
    state: PdrState, imu: ImuSamples, params: PdrParams
) -> tuple[np.ndarray, np.ndarray, bool, np.ndarray]:
    """Per accelerometer sample: an east-north-up quaternion (NaN rows: tilt only), the azimuth, whether
    every known azimuth is absolute, and the held gyroscope sample (NaN rows: none yet)."""
    t = imu.acc[:, 0]
    rv, state.rv_hold = _held(imu.rv, state.rv_hold, t)
    gyr, state.gyr_hold = _held(imu.gyr, state.gyr_hold, t)
    mag, state.mag_hold = _held(imu.mag, state.mag_hold, t)
    grv, state.grv_hold = _held(imu.grv, state.grv_hold, t)
    q = np.full((t.size, 4), np.nan)
    has_rv = np.isfinite(rv[:, 0])
    has_grv = ~has_rv & np.isfinite(grv[:, 0])
    for mask, rows in ((has_rv, rv), (has_grv, grv)):
        if mask.any():
            w = rows[mask, 3]
            q[mask] = quaternion_from_rotation_vector(rows[mask, :3], None if np.isnan(w).any() else w)
    absolute = not has_grv.any()
    fuse = ~has_rv & ~has_grv & np.isfinite(gyr[:, 0])
    if fuse.any():
        if np.isnan(state.q[0]):
            first = int(np.argmax(fuse))
            state.q = _start_quaternion(imu.acc[first, 1:4], mag[first])
        magnetic = np.isfinite(mag[fuse, 0])
        absolute = absolute and bool(magnetic.all())
        fused = madgwick_run(
            state.q,
            np.ascontiguousarray(t[fuse]),
            np.ascontiguousarray(gyr[fuse]),
            np.ascontiguousarray(imu.acc[fuse, 1:4]),
            np.ascontiguousarray(np.where(magnetic[:, None], mag[fuse], 0.0)),
            params.madgwick_gain,
            state.fused_t_ms,
        )
        state.fused_t_ms = float(t[fuse][-1])
        q[fuse] = _multiply(_NWU_TO_ENU, fused)
    return q, azimuth(q), absolute, gyr


def drop_stale(state: PdrState, imu: ImuSamples) -> tuple[ImuSamples, int]:
    """The batch without the samples at or before what this user's front-end has already consumed (a late
    or re-sent batch), and how many were dropped: the front-end never runs backwards in time."""
    kept = {}
    dropped = 0
    for name, last in (
        ("acc", state.steps[2]),
        ("gyr", state.gyr_hold[0]),
        ("mag", state.mag_hold[0]),
        ("rv", state.rv_hold[0]),
        ("grv", state.grv_hold[0]),
    ):
        rows = getattr(imu, name)
        if rows.size and not math.isnan(last) and rows[0, 0] <= last:
            fresh = rows[rows[:, 0] > last]
            dropped += rows.shape[0] - fresh.shape[0]
            rows = fresh
        kept[name] = rows
    return (ImuSamples(**kept, pressure=imu.pressure) if dropped else imu), dropped


def pdr_steps(state: PdrState, imu: ImuSamples, params: PdrParams) -> PdrSteps:
    """The steps completed in this batch; ``state`` is advanced in place (left untouched on bad input)."""
    t = imu.acc[:, 0]
    for name, rows, last in (
        ("acc", imu.acc, state.steps[2]),
        ("gyr", imu.gyr, state.gyr_hold[0]),
        ("mag", imu.mag, state.mag_hold[0]),
        ("rv", imu.rv, state.rv_hold[0]),
        ("grv", imu.grv, state.grv_hold[0]),
    ):
        if rows.size and not math.isnan(last) and rows[0, 0] <= last:
            raise ValueError(f"{name}: sample times must strictly increase, also across batches")
    if t.size == 0:
        for rows, name in (
            (imu.rv, "rv_hold"),
            (imu.grv, "grv_hold"),
            (imu.gyr, "gyr_hold"),
            (imu.mag, "mag_hold"),
        ):
            if rows.size:
                setattr(state, name, rows[-1].copy())
        return PdrSteps(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    q, yaw, absolute, gyr = _orientation(state, imu, params)
    offsets = None
    if (
        absolute
        and params.heading.gyro_heading
        and (np.isfinite(gyr[:, 0]).any() or not math.isnan(state.heading[0]))
    ):
        rate = np.full(t.size, np.nan)
        known = np.isfinite(q[:, 0]) & np.isfinite(gyr[:, 0])
        rate[known] = vertical_rate(gyr[known], q[known])
        offset_before = current_offset(state.heading)
        yaw, offsets = gyro_heading(state.heading, t, yaw, rate, params.heading)
    tilt_only = np.isnan(q[:, 0])
    vertical = np.empty(t.size)
    if (~tilt_only).any():
        vertical[~tilt_only] = vertical_acceleration(imu.acc[~tilt_only, 1:4], q[~tilt_only])
    if tilt_only.any():  # the measured acceleration's magnitude stands in for its vertical component
        vertical[tilt_only] = np.linalg.norm(imu.acc[tilt_only, 1:4], axis=1) - 9.80665
    step_t, lengths, step_yaw = detect_steps(state.steps, t, vertical, params.steps, yaw)
    lengths = np.clip(lengths, 0.1, 3.0)
    if absolute:
        turns = np.full(step_t.size, np.nan)
        step_offset = np.full(step_t.size, np.nan)
        if offsets is not None:  # the offset when the step peaked (before this batch: as it stood then)
            index = np.searchsorted(t, step_t, side="right") - 1
            step_offset = np.where(index >= 0, offsets[np.maximum(index, 0)], offset_before)
            step_yaw = (step_yaw + step_offset + math.pi) % (2 * math.pi) - math.pi
        return PdrSteps(step_t.astype(np.int64), lengths, step_yaw, turns, step_offset)
    previous = np.concatenate([[state.last_yaw], step_yaw[:-1]])
    turns = -((step_yaw - previous + math.pi) % (2 * math.pi) - math.pi)  # azimuth is clockwise
    turns = np.where(np.isfinite(turns), turns, 0.0)
    if step_yaw.size:
        state.last_yaw = float(step_yaw[-1])
    nan = np.full(step_t.size, np.nan)
    return PdrSteps(step_t.astype(np.int64), lengths, nan, turns, nan.copy())
