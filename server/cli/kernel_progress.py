"""What a start says while the filter's kernels warm up: on a cold cache they compile (about a minute, once),
and a start says so at once with a bar; later starts load them from numba's on-disk cache and run the
warm-up in a few seconds, and say nothing unless it takes far longer (a loaded machine), then that they are
loading."""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path
from typing import Any, TextIO

COMPILING = "compiling the filter's kernels: about a minute, once (later starts load them from the cache)"
LOADING = "loading the filter's kernels from the cache"
WARM_QUIET_S = 15.0
"""A warm start (a few seconds) says nothing unless its warm-up takes this long."""


class KernelProgress:
    """A ``create_app(warming=...)`` listener: when the warm-up has not ended ``quiet_s`` after it began, it
    says so on ``stream`` and shows a bar of its steps until it ends."""

    def __init__(
        self,
        prog: str = "crowdslam",
        stream: TextIO = sys.stderr,
        quiet_s: float = 1.5,
        cached: bool | None = None,
    ) -> None:
        """``cached``: whether numba's cache holds the kernels already (None: look, ``kernels_cached``); a
        warm start waits ``WARM_QUIET_S`` (or ``quiet_s`` if longer) before it says anything."""
        self.prog = prog
        self.stream = stream
        self.cached = kernels_cached() if cached is None else cached
        self.quiet_s = max(quiet_s, WARM_QUIET_S) if self.cached else quiet_s
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._bar: Any = None
        self._done = 0
        self._total = 1
        self._ended = False

    def __call__(self, done: int, total: int) -> None:
        with self._lock:
            self._done, self._total = done, total
            if self._timer is None and not self._ended:
                self._timer = threading.Timer(self.quiet_s, self._announce)
                self._timer.daemon = True
                self._timer.start()
            if self._bar is not None:
                self._bar.n = done
                self._bar.refresh()
            if done >= total:
                self._ended = True
                if self._timer is not None:
                    self._timer.cancel()
                if self._bar is not None:
                    self._bar.close()

    def _announce(self) -> None:
        from tqdm import tqdm

        with self._lock:
            if self._ended:
                return
            print(f"{self.prog}: {LOADING if self.cached else COMPILING}", file=self.stream, flush=True)
            self._bar = tqdm(
                total=self._total, initial=self._done, desc="kernels", unit="step", file=self.stream
            )


def kernels_cached() -> bool:
    """Whether numba's cache folder (keyed by the kernels' sources: ``server.slam.numba_cache``) holds
    compiled kernels: a folder without any index is a first start."""
    folder = os.environ.get("NUMBA_CACHE_DIR")
    return folder is not None and any(Path(folder).rglob("*.nbi"))
