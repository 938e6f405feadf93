"""``crowdslam import-msindoor DIR --out FILE.mcap``: public Indoor Location 2.0 walks as a recording, and the
floor's plan (its ``geojson_map.json``) beside it as ``FILE.plan.json``, ready for
``PUT /v1/buildings/{id}/floors/0/plan``. DIR may be a building (its floors as subfolders ``B1``, ``F1``,
``F2``, ...): every floor's walks go into the one recording, and each floor's plan beside it as
``FILE.<floor>.plan.json`` for ``PUT .../floors/<level>/plan``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from server.cli.user_errors import walks_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dir",
        type=walks_folder,
        help="a floor folder (with path_data_files/), a building of floor folders, or a folder of .txt walks",
    )
    parser.add_argument("--out", type=Path, required=True, help="the MCAP file to write")
    parser.add_argument("--building", default="msindoor", help="building id written into the batches")


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from tqdm import tqdm

    from server.datasets.msindoor import building_floors, read_floor, read_floor_plan, read_trace
    from server.datasets.msindoor_batches import trace_batches
    from server.recordings.recorder import BuildingRecorder

    floors: list[tuple[int, Path]] = []
    if not any(args.dir.glob("*.txt")):
        try:
            floors = building_floors(args.dir)
        except ValueError:
            floors = []
    building = len(floors) > 1 or (len(floors) == 1 and floors[0][1] != args.dir)
    folders = [f / "path_data_files" for _, f in floors] if floors else [args.dir]
    walks = sorted(w for folder in folders for w in folder.glob("*.txt"))
    staging = args.out.parent / f".{args.out.stem}-staging"
    recorder = BuildingRecorder(staging, args.building)
    t0 = time.time_ns()
    n = 0
    # walks are recorded one after another, each as its own device, batches in time order
    for walk in tqdm(walks, desc="walks", unit="walk"):
        for batch in trace_batches(read_trace(walk), args.building, f"walk-{walk.stem[:48]}"):
            recorder.record_batch(batch.model_dump_json(exclude_none=True).encode(), t0 + n)
            n += 1
    recorder.close()
    (produced,) = (staging / args.building).glob("*.mcap")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    produced.replace(args.out)
    (staging / args.building).rmdir()
    staging.rmdir()
    print(f"{len(walks)} walks, {n} batches -> {args.out}")
    for level, floor_dir in floors if building else [(0, args.dir)]:
        if not (floor_dir / "floor_info.json").is_file():
            continue
        reading = read_floor_plan(read_floor(floor_dir))
        plan = reading.plan
        if reading.skipped_features or reading.repaired_rings or reading.dropped_rings:
            print(
                f"floor plan {floor_dir.name}: {reading.skipped_features} features without a usable polygon "
                f"left out, {reading.repaired_rings} open rings closed, "
                f"{reading.dropped_rings} degenerate rings dropped"
            )
        if plan is not None:
            suffix = f".{floor_dir.name}.plan.json" if building else ".plan.json"
            plan_file = args.out.with_suffix(suffix)
            plan_file.write_text(plan.model_dump_json(exclude_none=True))
            print(
                f"floor plan ({len(plan.features)} features) -> {plan_file}; upload it with "
                f"PUT /v1/buildings/{args.building}/floors/{level}/plan"
            )
    return 0
