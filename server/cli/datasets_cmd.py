"""``crowdslam datasets fetch msindoor20 [--floors site1/F1 ...]``: the public walks the project measures on,
downloaded from their GitHub repository into the data directory, each file checked against the shipped
manifest."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    fetch = sub.add_parser(
        "fetch",
        help="download a public data set into the data directory",
        description="Download the Indoor Location Competition 2.0 sample (MIT licence) from its GitHub "
        "repository: the floors the project measures on, each file checked by its SHA-256.",
    )
    fetch.add_argument("name", choices=["msindoor20"], help="the data set")
    fetch.add_argument(
        "--floors",
        nargs="+",
        metavar="SITE/FLOOR",
        help="only these floors (e.g. site1/F1 site2/F2); all by default",
    )
    where = fetch.add_mutually_exclusive_group()
    where.add_argument("--ref", help="the repository's branch, tag or commit (default: master)")
    where.add_argument("--source", help="a mirror of the repository's raw files (its root URL)")
    fetch.add_argument(
        "--data-dir", type=Path, help="the data directory (default: CROWDSLAM_DATA_DIR, ./crowdslam-data)"
    )


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from tqdm import tqdm

    from server.cli.user_errors import UserError
    from server.datasets.fetch import (
        UPSTREAM,
        FetchError,
        as_source,
        dataset_dir,
        fetch,
        load_manifest,
        manifest_summary,
    )
    from server.settings import Settings

    data_dir = args.data_dir if args.data_dir is not None else Settings().data_dir
    root = dataset_dir(data_dir)
    source = args.source or (as_source(args.ref) if args.ref else UPSTREAM)
    try:
        files = load_manifest().select(args.floors)
        size = manifest_summary(files)["bytes"]
        with tqdm(total=size, unit="B", unit_scale=True, desc=args.name) as bar:
            fetched = fetch(root, files, source, progress=bar.update)
    except FetchError as exc:
        raise UserError(str(exc)) from None
    floors = sorted({"/".join(f.path.split("/")[:2]) for f in files if f.path.count("/") >= 2})
    print(
        f"{args.name}: {len(files)} files ({size / 1e6:.0f} MB) in {root}: {fetched.downloaded} downloaded, "
        f"{fetched.already_there} already there"
    )
    print(f"evaluate a floor: crowdslam evaluate --msindoor {root / floors[0]} --warm-split 0.5")
    return 0
