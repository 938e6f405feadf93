"""A child the server starts inside ``interrupts_held`` never sees a terminal's Ctrl-C, from its first
instruction: SIGINT is blocked in it. Also for the first child a process spawns, whose start starts
multiprocessing's resource tracker (which unblocks SIGINT in the starting thread once it runs)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.conftest import ROOT

SCRIPT = """
import multiprocessing, sys, threading
from server.process_lifetime import interrupts_held

def child(out):
    status = open("/proc/self/status").read().splitlines()
    with open(out, "a") as f:
        f.write(next(line for line in status if line.startswith("SigBlk")) + "\\n")

def start(out):
    with interrupts_held():
        process = multiprocessing.get_context("spawn").Process(target=child, args=(out,))
        process.start()
    process.join()

if __name__ == "__main__":
    start(sys.argv[1])  # the process's first spawn, from its main thread
    thread = threading.Thread(target=start, args=(sys.argv[1],))
    thread.start()
    thread.join()
"""


def test_children_started_inside_interrupts_held_have_sigint_blocked(tmp_path: Path) -> None:
    script, out = tmp_path / "spawn.py", tmp_path / "masks.txt"
    script.write_text(SCRIPT)
    subprocess.run([sys.executable, str(script), str(out)], timeout=120, cwd=ROOT, check=True)
    masks = [int(line.split()[1], 16) for line in out.read_text().splitlines()]
    assert len(masks) == 2
    assert all(mask & (1 << (2 - 1)) for mask in masks), masks  # SIGINT is signal 2
