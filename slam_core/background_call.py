"""A call that runs on another thread while its caller goes on, for compiled kernels that release the GIL
(``nogil``): a building's busy tracker call compares its WiFi scans on the machine's other core while it
runs the rounds of its filters and the fingerprint fixes. The result is the same as run inline; only the
time it takes changes.

The calls run on a few threads kept for the process's life (``WORKERS``): a thread started for each call
would cost its caller more than a busy building can spare."""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Generic, TypeVar

T = TypeVar("T")

WORKERS = 4
"""Calls running at once in a process (one per building at a time: its next call waits for this one)."""
_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _workers() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="background-call")
        return _pool


class BackgroundCall(Generic[T]):
    """``function()`` on a worker thread when ``background``, else now. ``result()`` waits and returns its
    value or raises its error in the caller's thread; ``join()`` only waits (for a caller that failed before
    collecting it). ``on_done`` runs once, in the caller's thread, after the call has ended."""

    def __init__(
        self,
        function: Callable[[], T],
        background: bool,
        on_done: Callable[[], None] | None = None,
    ) -> None:
        self._function = function
        self._on_done = on_done
        self._value: T | None = None
        self._error: BaseException | None = None
        self._future: Future[None] | None = None
        if background:
            self._future = _workers().submit(self._run)
        else:
            self._run()

    def _run(self) -> None:
        try:
            self._value = self._function()
        except BaseException as exc:  # handed to the caller's thread by result()
            self._error = exc

    def join(self) -> None:
        if self._future is not None:
            self._future.result()  # _run catches everything: this only waits
            self._future = None
        if self._on_done is not None:
            on_done, self._on_done = self._on_done, None
            on_done()

    def result(self) -> T:
        self.join()
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]  # set by _run when it did not raise
