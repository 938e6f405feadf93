"""``crowdslam simulate``: simulated phones posting to a live server."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from server.cli.user_errors import UserError
from server.data import scenario_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario",
        type=scenario_argument,
        required=True,
        metavar="NAME_OR_FILE",
        help="a shipped scenario (paper-testbed) or a scenario JSON file",
    )
    parser.add_argument("--post", required=True, metavar="URL", help="the server, e.g. http://127.0.0.1:8000")
    parser.add_argument("--building", required=True, help="building id (created if missing)")
    parser.add_argument("--key", required=True, help="an operator key (it mints the phones' device keys)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--speed", type=float, default=0.0, help="x real time; 0 = as fast as the server answers"
    )
    parser.add_argument("--json", type=Path, help="write the run's summary here")


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    import httpx
    from tqdm import tqdm

    from server.simulation.crowd_client import device_keys, post_crowd, prepare_building
    from slam_core.sim.simulation import Scenario, simulate

    try:
        scenario = Scenario.from_dict(json.loads(args.scenario.read_text()))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, json.JSONDecodeError):
            raise
        raise UserError(f"{args.scenario} is not a usable scenario: {exc!r}") from None
    sim = simulate(scenario, args.seed)
    with httpx.Client(base_url=args.post, timeout=60.0) as client:
        prepare_building(client, args.building, args.key, sim)
        keys = device_keys(client, args.building, args.key, len(sim.users))
        with tqdm(desc="batches", unit="batch") as bar:
            report = post_crowd(client, sim, args.building, keys, args.speed, progress=bar.update)
    summary = report.summary()
    print(json.dumps(summary, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=2))
    return 0 if report.errors == 0 else 1
