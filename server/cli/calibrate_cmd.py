"""``crowdslam calibrate --msindoor FLOOR_DIR --out FILE``: fit the encounter range models on labelled
cross-walk scan pairs and report each WiFi feature's precision and recall for pairs within 5 m.

``crowdslam calibrate --scenario FILE [--seed N] --out FILE``: fit both range models on the scenario's
separate calibration world (the server's bundled ``server/data/testbed_calibration.json`` is the paper
testbed's, seed 0)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from server.cli.user_errors import floor_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--msindoor",
        type=floor_folder,
        metavar="FLOOR_DIR",
        help="a floor of Indoor Location 2.0 walks",
    )
    source.add_argument(
        "--scenario",
        type=Path,
        metavar="FILE",
        help="a simulated scenario (fits on its calibration world, seed + 10007)",
    )
    parser.add_argument("--seed", type=int, default=0, help="the scenario's seed (with --scenario)")
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="FILE",
        help="calibration JSON (for CROWDSLAM_ENCOUNTER_CALIBRATION or evaluate --calibration)",
    )
    parser.add_argument(
        "--plot", type=Path, metavar="PNG", help="precision-recall plot; default: beside --out"
    )
    parser.add_argument(
        "--base",
        type=Path,
        metavar="FILE",
        help="calibration whose Bluetooth model is kept (default: the server's)",
    )


def run(args: argparse.Namespace) -> int:
    if args.scenario is not None:
        return _run_scenario(args)
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from server.datasets.msindoor import TraceFormatError
    from server.datasets.msindoor_calibration import calibrate_floor, plot_calibration
    from server.slam.config import load_calibration

    try:
        base = load_calibration(args.base)
        calibration, report, pairs = calibrate_floor(args.msindoor, base)
    except (TraceFormatError, ValueError, OSError) as error:
        print(f"crowdslam calibrate: {error}")
        return 2
    plot = args.plot or args.out.with_suffix(".png")
    plot_calibration(plot, pairs, report)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({**calibration.to_dict(), "report": report}, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    print(f"wrote {args.out} and {plot}")
    return 0


def _run_scenario(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from slam_core.sim.encounters import calibrate
    from slam_core.sim.simulation import Scenario

    try:
        scenario = Scenario.from_dict(json.loads(args.scenario.read_text()))
    except (OSError, ValueError, KeyError) as error:
        print(f"crowdslam calibrate: {args.scenario}: {error}")
        return 2
    try:
        calibration = calibrate(scenario, args.seed)
    except ValueError as error:  # e.g. a world with too few labelled pairs to fit a range model
        print(f"crowdslam calibrate: {args.scenario}: {error}")
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(calibration.to_dict(), indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0
