"""``crowdslam schema``: JSON Schemas for client developers, and valid example bodies."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from schemas.catalog import EXAMPLES, json_schemas


def add_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--out", type=Path, metavar="DIR", help="write one <Model>.json file per public model")
    group.add_argument("--example", choices=sorted(EXAMPLES), help="print a valid example body")


def write_schemas(out_dir: Path) -> list[Path]:
    """Write ``<Model>.json`` for every public model into ``out_dir``; returns the files written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, schema in json_schemas().items():
        path = out_dir / f"{name}.json"
        path.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        written.append(path)
    return written


def run(args: argparse.Namespace) -> int:
    if args.example:
        json.dump(EXAMPLES[args.example], sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    for path in write_schemas(args.out):
        print(path)
    return 0
