"""``crowdslam calibrate --msindoor FLOOR_DIR --out FILE``: fit the encounter range models on labelled
cross-walk scan pairs and report each WiFi feature's precision and recall for pairs within 5 m."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--msindoor",
        type=Path,
        required=True,
        metavar="FLOOR_DIR",
        help="a floor of Indoor Location 2.0 walks",
    )
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
    from server.app import load_calibration
    from server.datasets.msindoor import TraceFormatError
    from server.datasets.msindoor_calibration import calibrate_floor, plot_calibration

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
