"""``crowdslam replay FILE``: feed a recording through the ingestion path, offline or to a server."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from server.cli.user_errors import UserError

MCAP_MAGIC = b"\x89MCAP0\r\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="an MCAP recording (from the server or import-msindoor)")
    target = parser.add_mutually_exclusive_group(required=True)
    target.add_argument("--offline", action="store_true", help="in-process, on a fresh temporary SQLite")
    target.add_argument("--server", metavar="URL", help="post to a running server")
    parser.add_argument("--key", help="operator key (with --server)")
    parser.add_argument("--json", type=Path, help="write the summary and each user's last estimate here")


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from tqdm import tqdm

    from server.recordings.recorder import read_batches
    from server.replay import replay_offline, replay_to_server
    from server.settings import get_settings

    with args.file.open("rb") as stream:  # a missing file is the user's error, said in one line
        if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise UserError(f"{args.file} is not an MCAP recording")
    if args.server and not args.key:
        raise UserError("--server needs --key (an operator key)")
    with tqdm(desc="batches", unit="batch") as bar:
        if args.offline:
            report = replay_offline(read_batches(args.file), get_settings(), bar.update)
        else:
            import httpx

            with httpx.Client(base_url=args.server, timeout=60.0) as client:
                report = replay_to_server(read_batches(args.file), client, args.key, bar.update)
    summary = report.summary()
    counts = {k: v for k, v in summary.items() if k != "latest"}
    print(json.dumps(counts, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=2))
    return 0 if report.rejected == 0 else 1
