"""A process the server starts (a building's, a signal-map build's, the kernels' compile) lives no longer than
the server, and is stopped by it, not by a terminal's Ctrl-C."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
from collections.abc import Iterator


def die_with(parent_pid: int) -> None:
    """Be killed when the process that started this one dies (Linux); elsewhere the caller notices otherwise
    (a building's closed socket ends its loop). Ctrl-C is left to the parent: a terminal sends it to the
    whole process group, and the parent stops its children in order (a building's last snapshot first),
    where an interrupt would cut a child short in the middle of a transaction."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent_pid:  # the parent died before the line above
        os._exit(0)


@contextlib.contextmanager
def interrupts_held() -> Iterator[None]:
    """Start child processes inside this: Ctrl-C is blocked in the starting thread meanwhile, and a child
    inherits the blocked signal from its first instruction (``die_with`` then ignores it). A terminal's
    Ctrl-C reaches its whole process group; a child that saw it would print a traceback from wherever it
    was (importing numba, say) and die under its parent, which stops its children in order itself."""
    if sys.platform != "win32":
        from multiprocessing import resource_tracker

        # started on a first spawn, the resource tracker unblocks SIGINT in the calling thread once it runs
        # (multiprocessing blocks SIGINT and SIGTERM around its own start, then unblocks both): started
        # before the mask is set, it cannot undo it
        resource_tracker.ensure_running()
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
