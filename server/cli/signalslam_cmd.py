"""``crowdslam signalslam --msindoor FLOOR_DIR --json OUT [--plots DIR]``: the SignalSLAM protocol on a floor
of real walks (landmarks at each walk's ends, error at the intermediate waypoints, leave-walks-out
fingerprint localisation)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from server.cli.user_errors import floor_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--msindoor",
        type=floor_folder,
        required=True,
        metavar="FLOOR_DIR",
        help="a floor of Indoor Location 2.0 walks",
    )
    parser.add_argument("--json", type=Path, required=True, metavar="OUT", help="where to write the metrics")
    parser.add_argument(
        "--plots",
        type=Path,
        metavar="DIR",
        help="trajectories and signal maps as PNG, signal-map grids and the 5 m fingerprint database as JSON",
    )
    parser.add_argument("--folds", type=int, default=5, help="leave-walks-out folds of the fingerprint test")
    parser.add_argument(
        "--solver", choices=("lm", "isam2"), default="lm", help="batch Levenberg-Marquardt or iSAM2 in chunks"
    )
    parser.add_argument(
        "--modalities",
        default="wifi",
        help="signal kernels to multiply, comma-separated from wifi, bluetooth, magnetic (default: wifi)",
    )


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from tqdm import tqdm

    from server.datasets.msindoor import TraceFormatError
    from server.datasets.msindoor_signalslam import run_signalslam
    from slam_core.signalslam.graph import MODALITIES, SignalGraphParams

    if args.folds < 2:
        print("crowdslam signalslam: --folds must be at least 2")
        return 2
    modalities = tuple(m.strip() for m in args.modalities.split(",") if m.strip())
    unknown = [m for m in modalities if m not in MODALITIES]
    if unknown or not modalities:
        print(f"crowdslam signalslam: unknown modalities {unknown}; valid: {', '.join(MODALITIES)}")
        return 2
    with tqdm(total=3, desc="signalslam", unit="stage", bar_format="{desc}: {n}/{total} {postfix}") as bar:

        def progress(stage: str) -> None:
            bar.set_postfix_str(stage)
            bar.update(1)

        try:
            run_ = run_signalslam(
                args.msindoor,
                SignalGraphParams(modalities=modalities, solver=args.solver),
                folds=args.folds,
                progress=progress,
            )
        except (TraceFormatError, ValueError, OSError) as error:
            print(f"crowdslam signalslam: {error}")
            return 2
    result = run_.result
    if args.plots is not None:
        from server.datasets.signalslam_plots import plot_trajectories, write_maps

        written = plot_trajectories(args.plots, run_.prepared, run_.trajectories) + write_maps(
            args.plots, run_
        )
        result["plots"] = [str(p) for p in written]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    print(f"wrote {args.json}")
    return 0
