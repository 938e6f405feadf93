"""Crowd fingerprint map benchmark: what a located scan and a stored scan cost on a full map.

    python bench/fingerprints.py [--width 120 --height 80 --aps 60 --scans 30000] [--json OUT]

The floor of ``bench/load.py`` by default: APs placed at random, log-distance path loss with 4 dB noise, each
scan the 15 strongest APs. ``--scans`` scans at random places fill the map (``slam_core.crowd.fingerprints``,
the server's parameters: at most ``per_cell`` per cell, ``max_references`` in all); then as many fresh scans
are located (``locate``: the inverted-index kernel and the weighted kNN) and stored (``add``; the scans are a
minute apart, so a full cell takes each). Prints one JSON object: references and postings held, microseconds
per locate and per add (median of 5 passes, wall time on one thread), the share of scans located and their
median error in metres.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from server.slam.numba_cache import configure_numba_cache

configure_numba_cache()
from report import emit

from slam_core.crowd.fingerprints import CrowdFingerprints, FingerprintParams

SCAN_TOP = 15


def _scans(
    rng: np.random.Generator, aps: np.ndarray, size: tuple[float, float], n: int
) -> list[tuple[np.ndarray, list[str], np.ndarray]]:
    names = [f"02:00:00:00:{a // 256:02x}:{a % 256:02x}" for a in range(len(aps))]
    out = []
    for xy in rng.uniform((5.0, 5.0), (size[0] - 5.0, size[1] - 5.0), size=(n, 2)):
        d = np.hypot(*(aps - xy).T)
        rss = -40.0 - 25.0 * np.log10(np.maximum(d, 1.0)) + rng.normal(0.0, 4.0, len(aps))
        top = np.argsort(-rss)[:SCAN_TOP]
        out.append((xy, [names[i] for i in top], np.clip(rss[top], -99.0, -20.0)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=float, default=120.0)
    parser.add_argument("--height", type=float, default=80.0)
    parser.add_argument("--aps", type=int, default=60)
    parser.add_argument("--scans", type=int, default=30_000)
    parser.add_argument("--queries", type=int, default=2_000)
    parser.add_argument("--json", type=Path, metavar="OUT")
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    size = (args.width, args.height)
    aps = rng.uniform((0.0, 0.0), size, size=(args.aps, 2))
    fill = _scans(rng, aps, size, args.scans)
    queries = _scans(rng, aps, size, args.queries)
    fp = CrowdFingerprints(FingerprintParams(enabled=True))
    for i, (xy, bssids, rss) in enumerate(fill):
        fp.add(i % 2_000, xy, bssids, rss, i * 60_000)  # a minute apart: every scan is stored
    fp.locate(-1, queries[0][1], queries[0][2])  # compile outside the timing

    locate_us, errors = [], []
    for _ in range(5):
        started = time.perf_counter()
        found = [fp.locate(-1, bssids, rss) for _, bssids, rss in queries]
        locate_us.append((time.perf_counter() - started) / len(queries) * 1e6)
    errors = [float(np.hypot(*(f - q[0]))) for f, q in zip(found, queries, strict=True) if f is not None]
    add_us = []
    for n in range(5):
        started = time.perf_counter()
        for i, (xy, bssids, rss) in enumerate(queries):
            fp.add(i, xy, bssids, rss, (args.scans + n * len(queries) + i) * 60_000)
        add_us.append((time.perf_counter() - started) / len(queries) * 1e6)
    result = {
        "floor_m": list(size),
        "aps": args.aps,
        "references": len(fp),
        "postings": fp.postings,
        "locate_us": statistics.median(locate_us),
        "add_us": statistics.median(add_us),
        "located_share": len(errors) / len(queries),
        "median_error_m": statistics.median(errors) if errors else None,
    }
    emit(result, args.json)


if __name__ == "__main__":
    main()
