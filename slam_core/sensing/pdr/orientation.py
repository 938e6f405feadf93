"""Phone orientation: Madgwick's gradient-descent filter (Madgwick et al. 2011, as SignalSLAM III-A1 uses)
ported to numba from ``ahrs.filters.Madgwick`` term for term (that package is the test oracle, not the
runtime), and Android rotation-vector helpers.

Quaternions are [w, x, y, z] (Hamilton), rotating the phone frame into the earth frame (x east, y north,
z up for the rotation vector; the Madgwick frame is set by gravity and the magnetic field).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _product(
    pw: float, px: float, py: float, pz: float, qw: float, qx: float, qy: float, qz: float
) -> tuple[float, float, float, float]:
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


@njit(cache=True, nogil=True)
def madgwick_step(
    q: np.ndarray, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray, dt: float, gain: float
) -> None:
    """One Madgwick update of ``q`` in place: MARG when ``mag`` is non-zero, else IMU (Madgwick Eq. 12-34)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    qw, qx, qy, qz = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    g_norm = math.sqrt(gyr[0] * gyr[0] + gyr[1] * gyr[1] + gyr[2] * gyr[2])
    if g_norm == 0.0:
        q[0], q[1], q[2], q[3] = qw, qx, qy, qz
        return
    dw, dx, dy, dz = _product(qw, qx, qy, qz, 0.0, gyr[0], gyr[1], gyr[2])
    dw, dx, dy, dz = 0.5 * dw, 0.5 * dx, 0.5 * dy, 0.5 * dz  # Eq. 12
    m_norm = math.sqrt(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2])
    a_norm = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
    if a_norm > 0.0:
        ax, ay, az = acc[0] / a_norm, acc[1] / a_norm, acc[2] / a_norm
        # objective and Jacobian of the gravity term (Eq. 25-26)
        f0 = 2.0 * (qx * qz - qw * qy) - ax
        f1 = 2.0 * (qw * qx + qy * qz) - ay
        f2 = 2.0 * (0.5 - qx * qx - qy * qy) - az
        g0 = -2.0 * qy * f0 + 2.0 * qx * f1
        g1 = 2.0 * qz * f0 + 2.0 * qw * f1 - 4.0 * qx * f2
        g2 = -2.0 * qw * f0 + 2.0 * qz * f1 - 4.0 * qy * f2
        g3 = 2.0 * qx * f0 + 2.0 * qy * f1
        f_sq = f0 * f0 + f1 * f1 + f2 * f2
        if m_norm > 0.0:
            mx, my, mz = mag[0] / m_norm, mag[1] / m_norm, mag[2] / m_norm
            # earth-frame field direction (Eq. 45-46): h = q (0, m) q*
            hw, hx, hy, hz = _product(0.0, mx, my, mz, qw, -qx, -qy, -qz)
            hw, hx, hy, hz = _product(qw, qx, qy, qz, hw, hx, hy, hz)
            bx = math.sqrt(hx * hx + hy * hy)
            bz = hz
            f3 = 2.0 * bx * (0.5 - qy * qy - qz * qz) + 2.0 * bz * (qx * qz - qw * qy) - mx
            f4 = 2.0 * bx * (qx * qy - qw * qz) + 2.0 * bz * (qw * qx + qy * qz) - my
            f5 = 2.0 * bx * (qw * qy + qx * qz) + 2.0 * bz * (0.5 - qx * qx - qy * qy) - mz
            # Eq. 32, transposed and applied to f (Eq. 34)
            g0 += -2.0 * bz * qy * f3 + (-2.0 * bx * qz + 2.0 * bz * qx) * f4 + 2.0 * bx * qy * f5
            g1 += (
                2.0 * bz * qz * f3
                + (2.0 * bx * qy + 2.0 * bz * qw) * f4
                + (2.0 * bx * qz - 4.0 * bz * qx) * f5
            )
            g2 += (-4.0 * bx * qy - 2.0 * bz * qw) * f3 + (2.0 * bx * qx + 2.0 * bz * qz) * f4
            g2 += (2.0 * bx * qw - 4.0 * bz * qy) * f5
            g3 += (
                (-4.0 * bx * qz + 2.0 * bz * qx) * f3
                + (-2.0 * bx * qw + 2.0 * bz * qy) * f4
                + 2.0 * bx * qx * f5
            )
            f_sq += f3 * f3 + f4 * f4 + f5 * f5
        if f_sq > 0.0:
            g_len = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2 + g3 * g3)
            if g_len > 0.0:
                dw -= gain * g0 / g_len  # Eq. 33
                dx -= gain * g1 / g_len
                dy -= gain * g2 / g_len
                dz -= gain * g3 / g_len
    nw, nx, ny, nz = qw + dw * dt, qx + dx * dt, qy + dy * dt, qz + dz * dt  # Eq. 13
    n = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    q[0], q[1], q[2], q[3] = nw / n, nx / n, ny / n, nz / n


@njit(cache=True, nogil=True)
def madgwick_run(
    q: np.ndarray,
    t_ms: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray,
    gain: float,
    last_t_ms: float,
) -> np.ndarray:
    """Filter a batch; ``q`` (the state) is updated in place; returns the quaternion after every sample.
    ``dt`` comes from the timestamps (``last_t_ms`` is the previous batch's last sample, NaN at the start:
    the first sample then only sets the time). ``mag`` rows of zeros mean no magnetometer."""
    out = np.empty((t_ms.shape[0], 4))
    previous = last_t_ms
    for i in range(t_ms.shape[0]):
        if not math.isnan(previous):
            dt = (t_ms[i] - previous) * 1e-3
            if dt > 0.0:
                madgwick_step(q, gyr[i], acc[i], mag[i], dt, gain)
        previous = t_ms[i]
        out[i] = q
    return out


def quaternion_from_rotation_vector(xyz: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Android rotation vector (x, y, z[, w]) to [w, x, y, z]; w = sqrt(1 - |xyz|^2) when not sent."""
    xyz = np.asarray(xyz, dtype=float)
    if w is None:
        w = np.sqrt(np.clip(1.0 - np.sum(xyz * xyz, axis=-1), 0.0, None))
    q = np.concatenate([np.asarray(w, dtype=float)[..., None], xyz], axis=-1)
    normalised: np.ndarray = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return normalised


def azimuth(q: np.ndarray) -> np.ndarray:
    """Android ``getOrientation`` azimuth (rad, clockwise from north) of the phone's y axis for [w, x, y, z]
    quaternions rotating the phone frame into east-north-up: atan2(R[0,1], R[1,1])."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    r01 = 2.0 * (x * y - z * w)
    r11 = 1.0 - 2.0 * (x * x + z * z)
    result: np.ndarray = np.arctan2(r01, r11)
    return result
