"""A signal-map build's radio map: every WiFi scan of its walks at the position SignalSLAM placed it, the file
a building's tracker loads as fingerprints (``BuildingTracker.load_radio_map``). It joins the two papers: the
crowd's offline GraphSLAM map feeds the live DynamicSLAM filters the weak, outlier-robust fixes they already
take from the map the crowd learns at its estimates."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.signal_maps import SignalMapJob, SignalMapStatus

RADIO_MAP = "radio_map.json"
RECORD = "job.json"
"""A build's job record, beside its files (``server.signal_maps.jobs``)."""


@dataclass(frozen=True)
class RadioMap:
    map_id: str
    """The build's job id: a tracker loads each map once."""
    xy: np.ndarray
    """(n, 2) where each scan was taken, in the local frame."""
    bssids: list[list[str]]
    rss: list[np.ndarray]
    t_ms: np.ndarray
    levels: np.ndarray
    """The floor of each scan."""

    def __len__(self) -> int:
        return len(self.bssids)


def write_radio_map(
    folder: Path, xy: np.ndarray, scans: list[dict[str, float]], t_ms: np.ndarray, levels: np.ndarray
) -> Path:
    """Write the placed scans (fresh APs only, BSSIDs lower case) and their floors as ``radio_map.json``."""
    path = folder / RADIO_MAP
    rows = [
        {
            "t_ms": int(t),
            "floor": int(lv),
            "x_m": round(float(p[0]), 3),
            "y_m": round(float(p[1]), 3),
            "aps": scan,
        }
        for p, scan, t, lv in zip(xy, scans, t_ms, levels, strict=True)
    ]
    path.write_text(json.dumps({"scans": rows}))
    return path


def read_radio_map(path: Path, map_id: str) -> RadioMap:
    """A radio map file; ``ValueError`` when it is not one."""
    try:
        rows = json.loads(path.read_text())["scans"]
        xy = np.array([[r["x_m"], r["y_m"]] for r in rows], dtype=np.float64).reshape(-1, 2)
        bssids = [[str(b).lower() for b in r["aps"]] for r in rows]
        rss = [np.array(list(r["aps"].values()), dtype=np.float64) for r in rows]
        t_ms = np.array([int(r["t_ms"]) for r in rows], dtype=np.int64)
        levels = np.array([int(r.get("floor", 0)) for r in rows], dtype=np.int64)  # older maps: floor 0
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
        raise ValueError(f"{path} is not a radio map: {error}") from error
    if not (np.all(np.isfinite(xy)) and all(np.all(np.isfinite(r)) for r in rss)):
        raise ValueError(f"{path} holds non-finite positions or signal strengths")
    return RadioMap(map_id, xy, bssids, rss, t_ms, levels)


def latest_radio_map(root: Path, building_id: str, unless: str | None = None) -> RadioMap | None:
    """The radio map of the building's latest finished build under ``root`` (the signal maps' folder), or
    None when no finished build wrote one, or when the latest is build ``unless`` (already loaded: its file,
    which may be megabytes, is not read again)."""
    done = []
    for record in (root / building_id).glob(f"*/{RECORD}"):
        try:
            job = SignalMapJob.model_validate_json(record.read_text())
        except (OSError, ValueError):
            continue
        if job.status == SignalMapStatus.DONE and (record.parent / RADIO_MAP).is_file():
            done.append(job)
    if not done:
        return None
    latest = max(done, key=lambda j: (j.finished_at or j.created_at, j.id))
    if latest.id == unless:
        return None
    return read_radio_map(root / building_id / latest.id / RADIO_MAP, latest.id)
