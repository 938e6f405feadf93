"""A building's signal maps from its recordings (SignalSLAM), run in its own process by ``signal_maps``.

Every recorded batch is read back and converted as ingestion converts it. Per device, its steps (sent by the
phone, or dead-reckoned from raw IMU by the same front-end as live tracking), its landmarks (position fixes,
readings of operator-known anchors, tags with an encoded position) and its WiFi scans are put in time order;
each stretch between two consecutive landmarks with at least two steps becomes one walk of the SignalSLAM
graph (the paper's segments between NFC tags). The walks of each floor (both landmarks on it; a stretch
between landmarks of two floors is left out, as the paper keeps to one floor) are solved jointly; the scans
placed on the optimised trajectories give each floor's signal maps and 5 m fingerprint database, whose file
names start ``floor<level>_`` in a building of several floors, and one radio map of every floor's scans.

gtsam holds the GIL while it optimises, so this runs in a child process; the function takes and returns plain
data only.
"""

from __future__ import annotations

import itertools
import json
import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from schemas.sensors import SensorBatch
from server.datasets.signalslam_plots import LTE_CELL, MAGNETIC, write_column_maps, write_scan_maps
from server.ingestion.convert import BuildingContext, to_user_batch
from server.ingestion.radio_maps import write_radio_map
from server.recordings.recorder import read_batches
from slam_core.sensing.detectors import integrate_headings
from slam_core.sensing.pdr.heading import with_final_offset
from slam_core.sensing.pdr.online import PdrParams, PdrState, pdr_steps
from slam_core.signalslam.graph import SignalGraphParams, Walk, position_at, solve
from slam_core.signalslam.windows import (
    WINDOW_STEP_MS,
    rss_matrix,
    window_counts,
    window_mean_series,
    window_means,
    window_sightings,
)
from slam_core.wifi.pairs import STALE_AP_MS


@dataclass
class _Device:
    pdr: PdrState = field(default_factory=PdrState)
    step_t: list[int] = field(default_factory=list)
    step_len: list[float] = field(default_factory=list)
    step_azimuth: list[float] = field(default_factory=list)
    step_turn: list[float] = field(default_factory=list)
    step_offset: list[float] = field(default_factory=list)  # the PDR front-end's north offset, NaN: none
    fix_t: list[int] = field(default_factory=list)
    fix_xy: list[np.ndarray] = field(default_factory=list)
    fix_level: list[int] = field(default_factory=list)
    scan_t: list[int] = field(default_factory=list)
    scans: list[dict[int, float]] = field(default_factory=list)
    beacon_t: list[int] = field(default_factory=list)
    beacon_col: list[int] = field(default_factory=list)
    lte_t: list[int] = field(default_factory=list)
    lte: list[dict[int, float]] = field(default_factory=list)  # cell column -> RSRP (dBm)
    magnetic: list[np.ndarray] = field(default_factory=list)  # (M, 2) t, magnitude (uT) per batch


@dataclass
class _Columns:
    """The building's columns: WiFi APs, Bluetooth beacons and LTE cells, in first-seen order."""

    aps: dict[str, int] = field(default_factory=dict)
    beacons: dict[str, int] = field(default_factory=dict)
    cells: dict[str, int] = field(default_factory=dict)

    @staticmethod
    def names(index: dict[str, int]) -> list[str]:
        return sorted(index, key=index.__getitem__)


def _collect(files: list[str], ctx: BuildingContext, columns: _Columns) -> tuple[dict[str, _Device], int]:
    devices: dict[str, _Device] = defaultdict(_Device)
    skipped = 0
    batches: dict[tuple[str, str], SensorBatch] = {}
    for path in files:
        for recorded in read_batches(Path(path)):
            try:
                batch = SensorBatch.model_validate_json(recorded.raw)
            except ValidationError:
                skipped += 1  # recorded by an older schema: not ours to reinterpret
                continue
            # a batch recorded again by a building that replayed its log after a crash: the first is kept
            batches.setdefault((batch.device_id, batch.batch_id), batch)
    ordered = sorted(batches.values(), key=lambda b: (b.device_id, b.seq))
    params = PdrParams()
    for batch in ordered:
        d = devices[batch.device_id]
        user = to_user_batch(batch, ctx).user_batch
        if user.step_t.size:
            d.step_t += user.step_t.tolist()
            d.step_len += user.step_length.tolist()
            d.step_azimuth += user.step_azimuth.tolist()
            d.step_turn += user.step_turn.tolist()
            d.step_offset += [math.nan] * user.step_t.size
        elif user.imu is not None and user.imu.acc.size:
            try:
                steps = pdr_steps(d.pdr, user.imu, params)
            except ValueError:
                skipped += 1  # samples older than the device's previous batch
                continue
            d.step_t += steps.t_ms.tolist()
            d.step_len += steps.length_m.tolist()
            d.step_azimuth += steps.azimuth_rad.tolist()
            d.step_turn += steps.turn_rad.tolist()
            d.step_offset += steps.heading_offset_rad.tolist()
        d.fix_t += user.fix_t.tolist()
        d.fix_xy += list(user.fix_xy)
        d.fix_level += [user.fix_floor(i) for i in range(user.fix_t.size)]
        for k in range(user.scan_t.size):
            lo, hi = int(user.scan_offsets[k]), int(user.scan_offsets[k + 1])
            t = int(user.scan_t[k])
            entry = {
                columns.aps.setdefault(user.scan_bssid[i].lower(), len(columns.aps)): float(user.scan_rss[i])
                for i in range(lo, hi)
                if user.scan_last_seen[i] < 0 or user.scan_last_seen[i] >= t - STALE_AP_MS
            }
            if entry:
                d.scan_t.append(t)
                d.scans.append(entry)
        for k in range(user.beacon_t.size):
            d.beacon_t.append(int(user.beacon_t[k]))
            d.beacon_col.append(
                columns.beacons.setdefault(str(user.beacon_mac[k]).lower(), len(columns.beacons))
            )
        for cell in batch.lte:
            d.lte_t.append(cell.t_ms)
            d.lte.append({columns.cells.setdefault(cell.cell_id, len(columns.cells)): cell.rsrp_dbm})
        if batch.magnetometer is not None and batch.magnetometer.t_ms:  # phones counting steps send it too
            mag = batch.magnetometer
            magnitude = np.linalg.norm(np.column_stack([mag.x, mag.y, mag.z]), axis=1)
            d.magnetic.append(np.column_stack([np.asarray(mag.t_ms, dtype=float), magnitude]))
    return devices, skipped


@dataclass(frozen=True)
class _Segment:
    device: str
    level: int
    walk: Walk
    scan_t: np.ndarray
    scans: list[dict[int, float]]
    lte_t: np.ndarray
    lte: list[dict[int, float]]


def _offline_headings(headings: np.ndarray, azimuths: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """A walk's headings with the gyroscope yaw of the PDR front-end's steps referenced by the walk's last
    north offset (the map is built after the walk, so it may use the best estimate for all of it)."""
    referenced = np.pi / 2 - with_final_offset(azimuths, offsets)
    turned: np.ndarray = np.where(np.isfinite(offsets), referenced, headings)
    return turned


def _segments(devices: dict[str, _Device], columns: _Columns) -> tuple[list[_Segment], int]:
    """Every device's walks between consecutive landmarks on one floor, and how many were left out as
    crossing floors."""
    out = []
    across = 0
    for name, d in sorted(devices.items()):
        order = np.argsort(d.step_t, kind="stable")
        step_t = np.asarray(d.step_t, dtype=np.int64)[order]
        lengths = np.asarray(d.step_len)[order]
        headings = integrate_headings(np.asarray(d.step_azimuth), np.asarray(d.step_turn))[order]
        azimuths, offsets = np.asarray(d.step_azimuth)[order], np.asarray(d.step_offset)[order]
        fixes = sorted(zip(d.fix_t, d.fix_xy, d.fix_level, strict=True), key=lambda f: f[0])
        scan_t = np.asarray(d.scan_t, dtype=np.int64)
        lte_t = np.asarray(d.lte_t, dtype=np.int64)
        beacon_t, beacon_col = (
            np.asarray(d.beacon_t, dtype=np.int64),
            np.asarray(d.beacon_col, dtype=np.int64),
        )
        magnetic = np.vstack([np.zeros((0, 2)), *d.magnetic])
        magnetic = magnetic[np.argsort(magnetic[:, 0], kind="stable")]
        for (t0, xy0, level0), (t1, xy1, level1) in itertools.pairwise(fixes):
            inside = (step_t > t0) & (step_t <= t1)
            if inside.sum() < 2:
                continue
            if level0 != level1:
                across += 1
                continue
            in_scan = np.flatnonzero((scan_t >= t0) & (scan_t <= t1))
            in_lte = np.flatnonzero((lte_t >= t0) & (lte_t <= t1))
            lte = [d.lte[i] for i in in_lte]
            centres = np.arange(t0, t1 + 1, WINDOW_STEP_MS)
            counts = window_counts(centres, scan_t[in_scan], [d.scans[i] for i in in_scan], len(columns.aps))
            keep = counts.sum(axis=1) > 0
            walk = Walk(
                t_ms=np.concatenate([[t0], step_t[inside]]).astype(np.int64),
                lengths=lengths[inside],
                headings=_offline_headings(headings[inside], azimuths[inside], offsets[inside]),
                start=np.asarray(xy0, dtype=float),
                end=np.asarray(xy1, dtype=float),
                window_t=centres[keep].astype(np.int64),
                window_counts=counts[keep],
                window_beacons=window_sightings(centres, beacon_t, beacon_col, len(columns.beacons))[keep],
                window_magnetic=window_mean_series(centres, magnetic[:, 0], magnetic[:, 1])[keep],
                window_lte=window_means(centres, lte_t[in_lte], lte, len(columns.cells))[keep],
            )
            out.append(
                _Segment(
                    name, level0, walk, scan_t[in_scan], [d.scans[i] for i in in_scan], lte_t[in_lte], lte
                )
            )
    return out, across


def _write_maps(
    folder: Path,
    prefix: str,
    segments: list[_Segment],
    trajectories: list[np.ndarray],
    columns: _Columns,
    ctx: BuildingContext,
) -> list[Path]:
    """One floor's signal maps (WiFi, LTE, magnetic) and 5 m fingerprint database, their names after
    ``prefix``."""
    placed, rows, lte_xy, lte_rows, mag_xy, mag_values = [], [], [], [], [], []
    for segment, xy in zip(segments, trajectories, strict=True):
        t_ms = segment.walk.t_ms
        if segment.scan_t.size:
            placed.append(position_at(t_ms, xy, segment.scan_t.astype(float)))
            rows.append(rss_matrix(segment.scans, len(columns.aps)))
        if segment.lte_t.size:
            lte_xy.append(position_at(t_ms, xy, segment.lte_t.astype(float)))
            lte_rows.append(rss_matrix(segment.lte, len(columns.cells)))
        magnitude = segment.walk.window_magnetic
        if magnitude is not None and np.isfinite(magnitude).any():
            has = np.isfinite(magnitude)
            mag_xy.append(position_at(t_ms, xy, segment.walk.window_t[has].astype(float)))
            mag_values.append(magnitude[has, None])
    out = folder / f".{prefix}" if prefix else folder  # a floor's written apart, then named after it
    out.mkdir(exist_ok=True)
    written: list[Path] = []
    to_wgs84 = None if ctx.geo is None else ctx.geo.to_wgs84
    if rows:
        names = _Columns.names(columns.aps)
        written += write_scan_maps(out, np.vstack(placed), np.vstack(rows), names, to_wgs84=to_wgs84)
    if lte_rows:
        cells = _Columns.names(columns.cells)
        written += write_column_maps(
            out, np.vstack(lte_xy), np.vstack(lte_rows), cells, LTE_CELL, to_wgs84=to_wgs84
        )
    if mag_values:
        written += write_column_maps(
            out, np.vstack(mag_xy), np.vstack(mag_values), ["magnetic magnitude"], MAGNETIC, 1, to_wgs84
        )
    if not prefix:
        return written
    named = [p.rename(folder / f"{prefix}{p.name}") for p in written]
    out.rmdir()
    return named


def build_signal_maps(
    files: list[str], out_dir: str, ctx: BuildingContext, modalities: tuple[str, ...] = ("wifi",)
) -> dict[str, Any]:
    """Build and write the maps; returns the job's summary (segments, devices, files written). The
    signal edges use ``modalities`` (``SignalGraphParams.modalities``); the maps cover the most-heard WiFi
    APs and LTE cells and the magnetic magnitude, whatever the recordings hold."""

    columns = _Columns()
    devices, skipped = _collect(files, ctx, columns)
    segments, across = _segments(devices, columns)
    if not segments:
        raise ValueError(
            "no stretch of any device's steps lies between two landmarks (position fixes, known-anchor "
            "readings or tags with a position) on one floor: SignalSLAM needs a landmark at each end of a "
            "walk"
        )
    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    levels = sorted({s.level for s in segments})
    several = len(levels) > 1 or levels != [0]
    written: list[Path] = []
    placed: list[tuple[_Segment, np.ndarray]] = []
    tracks = []
    for level in levels:
        mine = [s for s in segments if s.level == level]
        trajectories = solve([s.walk for s in mine], SignalGraphParams(modalities=modalities))
        prefix = f"floor{level}_" if several else ""
        written += _write_maps(folder, prefix, mine, trajectories.signalslam, columns, ctx)
        for segment, xy in zip(mine, trajectories.signalslam, strict=True):
            if segment.scan_t.size:
                placed.append((segment, position_at(segment.walk.t_ms, xy, segment.scan_t.astype(float))))
            tracks.append(
                {
                    "device_id": segment.device,
                    "floor": level,
                    "t_ms": segment.walk.t_ms.tolist(),
                    "xy_m": np.round(xy, 3).tolist(),
                }
            )
    if (
        placed
    ):  # every scan at its SignalSLAM position, on its floor: the radio map the building's tracker loads
        names = _Columns.names(columns.aps)
        scans = [{names[c]: rss for c, rss in scan.items()} for s, _ in placed for scan in s.scans]
        written.append(
            write_radio_map(
                folder,
                np.vstack([xy for _, xy in placed]),
                scans,
                np.concatenate([s.scan_t for s, _ in placed]),
                np.concatenate([np.full(s.scan_t.size, s.level, dtype=np.int64) for s, _ in placed]),
            )
        )
    path = folder / "trajectories.json"
    path.write_text(json.dumps(tracks))
    written.append(path)
    return {
        "segments": len(segments),
        "segments_across_floors": across,
        "floors": levels,
        "devices": len({s.device for s in segments}),
        "scans": int(sum(s.scan_t.size for s in segments)),
        "access_points": len(columns.aps),
        "batches_skipped": skipped,
        "files": [p.name for p in written],
    }
