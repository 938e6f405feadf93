"""A radio map from walks tagged at both ends, built by the server's own signal-map build: what a building
gets once phones that met a tag (or a position fix) at each end of a walk have been recorded. The
evaluation of real floors builds its warm walks into one this way, with each walk's first and last
surveyed waypoints as its tags, as SignalSLAM assumes."""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path

from schemas.common import Position
from schemas.sensors import PositionFix
from server.datasets.msindoor import Trace
from server.datasets.msindoor_batches import trace_windows
from server.datasets.msindoor_replay import START_SIGMA_M
from server.ingestion.convert import BuildingContext
from server.ingestion.radio_maps import RADIO_MAP, RadioMap, read_radio_map
from server.recordings.recorder import BuildingRecorder
from server.signal_maps.build import build_signal_maps


def radio_map_of_walks(
    traces: Sequence[Trace],
    ctx: BuildingContext,
    modalities: tuple[str, ...] = ("wifi",),
    map_id: str = "tagged-walks",
) -> RadioMap | None:
    """Record the walks of a one-floor building (``ctx``, as its tracker converts batches) as phones would
    post them, with a position fix at each walk's first and last waypoint, build their signal maps as a
    server build does, and return the build's radio map; None when no walk has two waypoints."""
    if len(ctx.floors) != 1:
        raise ValueError(f"a radio map of walks is built for one floor; the building has {len(ctx.floors)}")
    (floor,) = ctx.floors
    building = ctx.building_id
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        recorder = BuildingRecorder(root / "recordings", building)
        n = 0
        for trace in traces:
            if len(trace.waypoints) < 2:
                continue
            tags = [trace.waypoints[0], trace.waypoints[-1]]
            cuts = [int(t[0]) for t in tags]
            for end, batch in trace_windows(trace, building, f"walk-{trace.path.stem[:48]}", cuts=cuts):
                due = [t for t in tags if t[0] < end]
                tags = [t for t in tags if t[0] >= end]
                if due:
                    fixes = [
                        PositionFix(
                            t_ms=int(t[0]),
                            position=Position(x_m=float(t[1]), y_m=float(t[2])),
                            sigma_m=START_SIGMA_M,
                            floor=floor,
                        )
                        for t in due
                    ]
                    batch = batch.model_copy(update={"landmarks": [*batch.landmarks, *fixes]})
                recorder.record_batch(batch.model_dump_json(exclude_none=True).encode(), n)
                n += 1
        recorder.close()
        files = [str(p) for p in sorted((root / "recordings" / building).glob("*.mcap"))]
        if not files:
            return None
        out = root / "build"
        try:
            build_signal_maps(files, str(out), ctx, modalities)
        except ValueError:  # no walk between two tags
            return None
        return read_radio_map(out / RADIO_MAP, map_id)
