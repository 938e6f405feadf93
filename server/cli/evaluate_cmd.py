"""``crowdslam evaluate``: run the simulated testbed (or a sweep), or replay a floor of real Indoor Location
2.0 walks as a crowd, through the server's own tracker, and write the metrics as JSON (+ a CDF plot)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from server.cli.user_errors import floor_folder, output_file
from server.data import scenario_argument

if TYPE_CHECKING:
    from collections.abc import Callable

    from server.slam.config import ReplayOptions


PLAN_ALIGNED_SHARE = 0.95
"""Below this share of surveyed waypoints on the plan's walkable area, the replay warns that the plan may be
misplaced (every waypoint of both shipped floors lies on theirs)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    world = parser.add_mutually_exclusive_group(required=True)
    world.add_argument(
        "--scenario",
        type=scenario_argument,
        metavar="NAME_OR_FILE",
        help="a shipped scenario (paper-testbed: the DynamicSLAM testbed) or a scenario JSON file",
    )
    world.add_argument(
        "--msindoor",
        type=floor_folder,
        metavar="FLOOR_DIR",
        help="a floor of Indoor Location 2.0 walks (crowdslam datasets fetch msindoor20 puts them in "
        "crowdslam-data/datasets/msindoor20/SITE/FLOOR), or a building (SITE: its floors B1, F1, F2, ... as "
        "levels -1, 0, 1, ...), replayed as a crowd",
    )
    parser.add_argument(
        "--warm-split",
        type=float,
        metavar="F",
        help="with --msindoor: the earliest fraction F of each floor's walks first builds the map; the rest "
        "is scored",
    )
    parser.add_argument(
        "--warm-pick",
        choices=("earliest", "alternate"),
        default="earliest",
        help="with --msindoor: which walks warm the crowd: the earliest (--warm-split's share; a building on "
        "its first day) or every other walk by start time (alternate: a building walked everywhere)",
    )
    parser.add_argument(
        "--zones",
        action="store_true",
        help="draw a zone per room (--scenario) or shop (--msindoor): its frontage, 4 m around it; report "
        'under "zones" the visits the server tells against the true ones (visit_f1, enter_delay_p50_s, '
        "false_transitions_per_hour), and the same for a point test of the estimates (naive)",
    )
    parser.add_argument(
        "--calibration",
        type=Path,
        metavar="FILE",
        help="with --msindoor: encounter range models from `crowdslam calibrate` (default: the server's)",
    )
    parser.add_argument("--seed", type=int, default=0, help="the simulated world's seed (and the filters')")
    parser.add_argument(
        "--filter-seed",
        type=int,
        metavar="N",
        help="the filters' own seed, when it should differ from --seed (their noise on one world)",
    )
    parser.add_argument("--mode", choices=("pdr", "semanticslam", "dynamicslam"), default="dynamicslam")
    parser.add_argument("--sampling", choices=("one-shot", "iterative"), default="iterative")
    parser.add_argument("--particles", type=int, default=75)
    parser.add_argument("--motion-model", choices=("paper", "bias-scale"), default="bias-scale")
    parser.add_argument(
        "--crowd-solver",
        choices=("graph", "fusion"),
        default="graph",
        help="shared anchor map: joint least squares (graph) or sequential fusion of estimates",
    )
    parser.add_argument(
        "--fingerprints",
        action=argparse.BooleanOptionalAction,
        help="dynamicslam: also localise scans on the WiFi fingerprint map the crowd learns (robust fixes; "
        "on by default, as on the server)",
    )
    parser.add_argument(
        "--liars",
        type=int,
        default=0,
        metavar="N",
        help="with --scenario: N simulated users lie (copied scans, made-up sightings, false fixes); only "
        "the honest users are scored",
    )
    parser.add_argument(
        "--no-floor-plan",
        dest="floor_plan",
        action="store_false",
        help="with --msindoor: do not weigh steps by the floor's plan (geojson_map.json)",
    )
    parser.add_argument(
        "--heading-axes",
        action="store_true",
        help="with a floor plan: also weigh each straight stretch of a walk by how well it follows the "
        "plan's grid (heuristic drift elimination; off by default)",
    )
    parser.add_argument(
        "--no-start-fix",
        dest="start_fix",
        action="store_false",
        help="with --msindoor and a warm crowd: the scored walks get no fix at their first waypoint; the "
        "crowd's map places them (reports seconds_to_5m)",
    )
    parser.add_argument(
        "--radio-map",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="with --msindoor --warm-split: build the warm walks into a radio map (SignalSLAM, each walk "
        "tagged at its first and last waypoints, as a server's signal-map build) that the tracker loads",
    )
    parser.add_argument(
        "--floors-alone",
        action="store_true",
        help="with --msindoor SITE (a building): also replay each floor alone and report, per floor, its "
        "figures in the building against alone (floors_alone)",
    )
    parser.add_argument("--sweep", choices=("particles", "density", "anchor-density"))
    parser.add_argument(
        "--compare",
        action="store_true",
        help="run pdr, semanticslam and dynamicslam (with --msindoor and a warm crowd, also dynamicslam "
        "with no start fix); their CDFs on one figure (Figure 14)",
    )
    parser.add_argument(
        "--json", type=output_file, required=True, metavar="OUT", help="where to write the metrics"
    )
    parser.add_argument(
        "--plot", type=output_file, metavar="PNG", help="CDF (or sweep) plot; default: beside --json"
    )


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from slam_core.sim.simulation import Scenario

    if args.msindoor is not None:
        return _msindoor(args)
    if args.warm_split is not None or args.calibration is not None or args.warm_pick != "earliest":
        print("crowdslam evaluate: --warm-split, --warm-pick and --calibration apply to --msindoor only")
        return 2

    try:
        scenario = Scenario.from_dict(json.loads(args.scenario.read_text()))
    except (OSError, json.JSONDecodeError, ValueError, KeyError) as error:
        print(f"crowdslam evaluate: cannot use scenario {args.scenario}: {error}")
        return 2
    plot = args.plot or args.json.with_suffix(".png")
    try:
        if args.sweep:
            result = _sweep(scenario, args, plot)
        elif args.compare:
            result = _compare(scenario, args, plot)
        else:
            result = _single(scenario, args, plot)
    except ValueError as error:  # a world the models cannot be calibrated or run on
        print(f"crowdslam evaluate: cannot evaluate scenario {args.scenario}: {error}")
        return 2
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    print(f"wrote {args.json} and {plot}")
    if not args.sweep:
        runs = result if args.compare else {args.mode: result}
        for mode, r in runs.items():
            print(summary(f"{scenario['name']} seed {args.seed}", mode, r))
    return 0


def summary(world: str, run: str, result: dict[str, Any]) -> str:
    """The line a run ends with: its errors' median and p90, and the share on the right floor where floors
    are told apart."""
    line = f"{world}, {run}: median {result['median_m']:.2f} m, p90 {result['p90_m']:.2f} m"
    floor = result.get("right_floor")
    if floor is not None and len(result.get("levels", [0, 1])) > 1:
        line += f", {floor:.1%} on the right floor"
    n = result.get("n_estimates") or result.get("n_waypoints")
    if n is not None:
        line += f", {n:,} scored"
    return line


def _msindoor(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from dataclasses import replace
    from functools import partial

    from tqdm import tqdm

    from server.datasets.msindoor import TraceFormatError, building_floors
    from server.datasets.msindoor_replay import floors_alone, replay_msindoor
    from server.settings import Settings
    from server.signal_maps.tagged_walks import radio_map_of_walks
    from server.slam.config import load_calibration, tracker_params
    from slam_core.sim.statistics import empirical_cdf
    from slam_core.tracking.params import MODES

    if args.sweep or args.liars:
        print("crowdslam evaluate: --sweep and --liars apply to --scenario only")
        return 2
    if args.floors_alone and len(building_floors(args.msindoor)) < 2:
        print("crowdslam evaluate: --floors-alone compares a building's floors; give a building (SITE)")
        return 2
    try:
        options = _replay_options(args)
        calibration = load_calibration(args.calibration)
    except (OSError, ValueError) as error:
        print(f"crowdslam evaluate: {error}")
        return 2
    runs = [(mode, replace(options, mode=mode)) for mode in (MODES if args.compare else (args.mode,))]
    if args.compare and options.warms and options.start_fix:
        runs.append(("no-start-fix", replace(options, mode="dynamicslam", start_fix=False)))
    results: dict[str, Any] = {}
    lines = []
    for name, run_options in runs:
        with tqdm(desc=f"replay {args.msindoor.name} ({name})", unit="batch") as bar:

            def progress(n: int, total: int) -> None:
                bar.total = total
                bar.update(n)

            try:
                params = tracker_params(Settings())
                result, errors = replay_msindoor(
                    args.msindoor,
                    run_options,
                    params,
                    calibration,
                    progress,
                    radio_map_of_walks if options.radio_map else None,
                )
            except (TraceFormatError, ValueError, OSError) as error:
                print(f"crowdslam evaluate: {error}")
                return 2
        if args.floors_alone:
            opened: list[Any] = []
            try:
                result["floors_alone"] = floors_alone(
                    args.msindoor, result, run_options, params, calibration, partial(_floor_bar, opened, name)
                )
            finally:
                for floor_bar in opened:
                    floor_bar.close()
        results[name] = result
        readings = result["floor_plan_reading"] or {}
        per_floor = readings.items() if result["per_floor"] is not None else [("", readings)]
        for level, reading in per_floor if name == runs[0][0] else []:
            on_plan = reading.get("waypoints_walkable")
            if on_plan is not None and on_plan < PLAN_ALIGNED_SHARE:
                which = f"floor {level}" if level else "floor"
                print(
                    f"crowdslam evaluate: warning: only {on_plan:.0%} of the {which}'s "
                    "surveyed waypoints lie in its plan's walkable area; the plan may not line up with the "
                    "floor (compare with --no-floor-plan)"
                )
        x, p = empirical_cdf(errors)
        lines.append((x, p, f"{name} (median {result['median_m']:.2f} m, p90 {result['p90_m']:.2f} m)"))
    plot = args.plot or args.json.with_suffix(".png")
    floor = "/".join(args.msindoor.resolve().parts[-2:])
    title = f"{floor} crowd replay" + (f", warm split {args.warm_split}" if args.warm_split else "")
    if args.warm_pick == "alternate":
        title += ", every other walk warms"
    if not options.floor_plan:
        title += ", no floor plan"
    _plot_lines(plot, lines, "waypoint error (m)", "CDF", title)
    out = results if args.compare else results[runs[0][0]]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
    print(f"wrote {args.json} and {plot}")
    for name, r in results.items():
        print(summary(floor, name, r))
    return 0


def _floor_bar(opened: list[Any], run: str, folder: str) -> Callable[[int, int], None]:
    """A progress bar for a floor replayed alone (kept in ``opened`` to be closed), as a replay's callback."""
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from tqdm import tqdm

    bar = tqdm(desc=f"replay {folder} alone ({run})", unit="batch")
    opened.append(bar)

    def tick(n: int, total: int) -> None:
        bar.total = total
        bar.update(n)

    return tick


def _run(scenario: Any, args: argparse.Namespace, mode: str, particles: int, bar: Any) -> tuple[Any, Any]:
    """One run of the scenario through the server's tracker (``server.simulation.evaluation``)."""
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from dataclasses import replace

    from server.settings import Settings
    from server.simulation.evaluation import evaluate_scenario
    from server.slam.config import load_calibration, tracker_params

    options = replace(_replay_options(args), mode=mode, particles=particles)
    return evaluate_scenario(
        scenario, options, tracker_params(Settings()), load_calibration(None), bar.update
    )


def _single(scenario: Any, args: argparse.Namespace, plot: Path) -> dict[str, Any]:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from tqdm import tqdm

    from slam_core.sim.statistics import empirical_cdf

    with tqdm(desc=f"{scenario['name']} ({args.mode})", unit="batch") as bar:
        result, errors = _run(scenario, args, args.mode, args.particles, bar)
    x, p = empirical_cdf(errors)
    _plot_lines(
        plot, [(x, p, args.mode)], "position error (m)", "CDF", f"{scenario['name']} seed {args.seed}"
    )
    return dict(result)


def _compare(scenario: Any, args: argparse.Namespace, plot: Path) -> dict[str, Any]:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from tqdm import tqdm

    from slam_core.sim.statistics import empirical_cdf
    from slam_core.tracking.params import MODES

    results, lines = {}, []
    for mode in MODES:
        with tqdm(desc=f"{scenario['name']} ({mode})", unit="batch") as bar:
            result, errors = _run(scenario, args, mode, args.particles, bar)
        results[mode] = result
        x, p = empirical_cdf(errors)
        lines.append((x, p, f"{mode} (median {result['median_m']:.2f} m)"))
    _plot_lines(plot, lines, "position error (m)", "CDF", f"{scenario['name']} seed {args.seed}")
    return results


def _sweep(scenario: Any, args: argparse.Namespace, plot: Path) -> dict[str, Any]:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from tqdm import tqdm

    from slam_core.sim import sweeps

    rows = []
    modes = ("semanticslam", "dynamicslam")
    values = sweeps.sweep_values(args.sweep)
    with tqdm(total=len(values) * len(modes), desc=f"sweep {args.sweep}", unit="run") as bar:
        for value in values:
            world = sweeps.swept_scenario(scenario, args.sweep, value)
            particles = int(value) if args.sweep == "particles" else args.particles
            for mode in modes:
                r, _ = _run(world, args, mode, particles, _Ignore())
                rows.append(
                    {
                        "value": value,
                        "mode": mode,
                        "median_m": r["median_m"],
                        "p90_m": r["p90_m"],
                        "seconds": r["seconds"],
                    }
                )
                bar.update()
    print(f"{args.sweep:>14} {'mode':>13} {'median_m':>9} {'p90_m':>7}")
    for row in rows:
        print(f"{row['value']:>14} {row['mode']:>13} {row['median_m']:>9.2f} {row['p90_m']:>7.2f}")
    lines = [
        ([r["value"] for r in rows if r["mode"] == m], [r["median_m"] for r in rows if r["mode"] == m], m)
        for m in modes
    ]
    xlabel = {
        "particles": "particles",
        "density": "m^2 per user",
        "anchor-density": "m^2 per building anchor",
    }[args.sweep]
    _plot_lines(
        plot,
        lines,
        xlabel,
        "median error (m)",
        f"sweep of {args.sweep}, seed {args.seed}",
        log_x=args.sweep != "particles",
    )
    return {"sweep": args.sweep, "seed": args.seed, "rows": rows}


class _Ignore:
    """A progress bar that shows nothing (a sweep shows one bar for its runs)."""

    def update(self, n: int = 1) -> None:
        pass


def _plot_lines(
    path: Path, lines: list[Any], xlabel: str, ylabel: str, title: str, log_x: bool = False
) -> None:
    # deferred: matplotlib loads only when plotting, its backend chosen before pyplot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for x, y, label in lines:
        ax.plot(x, y, marker="o" if len(x) < 20 else None, label=label)
    if log_x:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _replay_options(args: argparse.Namespace) -> ReplayOptions:
    """The command's options for a replay through the server's tracker (real walks or simulated phones)."""
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from server.slam.config import ReplayOptions  # imported late: the CLI starts fast

    return ReplayOptions(
        mode=args.mode,
        warm_split=args.warm_split,
        warm_pick=args.warm_pick,
        particles=args.particles,
        sampling=args.sampling,
        motion_model=args.motion_model,
        crowd_solver=args.crowd_solver,
        seed=args.seed,
        filter_seed=args.filter_seed,
        liars=args.liars,
        fingerprints=args.fingerprints is not False,
        floor_plan=args.floor_plan,
        radio_map=args.radio_map,
        start_fix=args.start_fix,
        heading_axes=args.heading_axes,
        zones=args.zones,
    )
