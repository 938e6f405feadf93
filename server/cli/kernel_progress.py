"""What a first start says while the filter's kernels compile (about a minute on a cold cache, once; later
starts load them from numba's on-disk cache in a second or two, and say nothing)."""

from __future__ import annotations

import sys
import threading
from typing import Any, TextIO

COMPILING = "compiling the filter's kernels: about a minute, once (later starts load them from the cache)"


class KernelProgress:
    """A ``create_app(warming=...)`` listener: when the warm-up has not ended ``quiet_s`` after it began, it
    says so on ``stream`` and shows a bar of its steps until it ends."""

    def __init__(self, prog: str = "crowdslam", stream: TextIO = sys.stderr, quiet_s: float = 1.5) -> None:
        self.prog = prog
        self.stream = stream
        self.quiet_s = quiet_s
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
            print(f"{self.prog}: {COMPILING}", file=self.stream, flush=True)
            self._bar = tqdm(
                total=self._total, initial=self._done, desc="kernels", unit="step", file=self.stream
            )
