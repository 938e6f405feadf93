"""A benchmark run against another commit, alternately, in one sitting: the only comparison of speeds this
machine allows (its speed drifts by up to three times over hours).

    python bench/against.py REF [--rounds 4] [--discard 1] [--figure cpu_us_per_batch] [--json OUT] \\
        [--here-args "ARGS"] -- bench/building.py --phones 2000 --group 40 --seconds 12

``REF`` (a commit, a tag, a branch) is checked out in a temporary git worktree; each round runs the
benchmark script once in this tree and once in that one, in swapped order every other round, each in a
fresh process whose imports come from its own tree (``PYTHONPATH``). The first ``--discard`` rounds warm
both trees' numba caches and are not counted. Prints one JSON object: each round's ``--figure`` (read from
the benchmark's ``--json`` output) here and there and their ratio, and the ratios' mean, least and greatest.

``REF`` ``.`` is this tree on both sides, and ``--here-args`` adds arguments to this side's runs only: the
same code with and without an option (``--here-args "--zones 100"``), alternately.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from report import emit


def _figure(tree: Path, script: str, args: list[str], figure: str) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        env = {**os.environ, "PYTHONPATH": str(tree)}
        done = subprocess.run(
            [sys.executable, str(tree / script), *args, "--json", str(out)],
            cwd=tree,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        if done.returncode != 0:
            raise SystemExit(f"{script} failed in {tree}:\n{done.stderr[-2000:]}")
        value = json.loads(out.read_text())[figure]
        return float(value)


def run(
    ref: str, rounds: int, discard: int, figure: str, command: list[str], here_args: list[str] | None = None
) -> dict[str, Any]:
    if not command:
        raise SystemExit("give the benchmark after --, e.g. -- bench/building.py --phones 2000")
    script, args = command[0], command[1:]
    extra = {"here": here_args or [], "there": []}
    with tempfile.TemporaryDirectory() as tmp:
        there = ROOT if ref == "." else Path(tmp) / "tree"
        if ref != ".":
            subprocess.run(
                ["git", "worktree", "add", "--detach", str(there), ref],
                cwd=ROOT,
                check=True,
                capture_output=True,
            )
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=there, check=True, capture_output=True, text=True
        ).stdout.strip()
        try:
            measured = []
            for r in range(discard + rounds):
                order = [("here", ROOT), ("there", there)]
                if r % 2:
                    order.reverse()
                values = {name: _figure(tree, script, [*args, *extra[name]], figure) for name, tree in order}
                if r >= discard:
                    measured.append(
                        {**values, "ratio": round(values["here"] / values["there"], 3), "first": order[0][0]}
                    )
                print(f"round {r + 1}: {values}", file=sys.stderr)
        finally:
            if ref != ".":
                subprocess.run(
                    ["git", "worktree", "remove", "--force", str(there)], cwd=ROOT, capture_output=True
                )
    ratios = [m["ratio"] for m in measured]
    return {
        "against": ref,
        "against_commit": commit,
        "benchmark": " ".join(command),
        "here_args": " ".join(extra["here"]),
        "figure": figure,
        "rounds": measured,
        "ratio_mean": round(statistics.fmean(ratios), 3),
        "ratio_min": min(ratios),
        "ratio_max": max(ratios),
    }


def main() -> int:
    argv = sys.argv[1:]
    command: list[str] = []
    if "--" in argv:
        at = argv.index("--")
        argv, command = argv[:at], argv[at + 1 :]
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("ref", help="the commit to measure against")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--discard", type=int, default=1, help="rounds run first and not counted")
    parser.add_argument("--figure", default="cpu_us_per_batch", help="the benchmark's JSON field compared")
    parser.add_argument("--json", type=Path, help="also write the result here")
    parser.add_argument("--here-args", default="", help="arguments added to this tree's runs only")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.discard < 0:
        parser.error("--rounds must be at least 1 and --discard at least 0")
    extra = shlex.split(args.here_args)
    emit(run(args.ref, args.rounds, args.discard, args.figure, command, extra), args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
