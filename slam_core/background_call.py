"""A call that runs on a thread of its own while its caller goes on, for compiled kernels that release the
GIL (``nogil``): a building's busy tracker call compares its WiFi scans on the machine's other core while it
runs the rounds of its filters and the fingerprint fixes. The result is the same as run inline;
only the time it takes changes."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class BackgroundCall(Generic[T]):
    """``function()`` on a thread of its own when ``background``, else now. ``result()`` waits and returns
    its value or raises its error in the caller's thread; ``join()`` only waits (for a caller that failed
    before collecting it). ``on_done`` runs once, in the caller's thread, after the call has ended."""

    def __init__(
        self,
        function: Callable[[], T],
        background: bool,
        name: str,
        on_done: Callable[[], None] | None = None,
    ) -> None:
        self._function = function
        self._on_done = on_done
        self._value: T | None = None
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        if background:
            self._thread = threading.Thread(target=self._run, name=name, daemon=True)
            self._thread.start()
        else:
            self._run()

    def _run(self) -> None:
        try:
            self._value = self._function()
        except BaseException as exc:  # handed to the caller's thread by result()
            self._error = exc

    def join(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._on_done is not None:
            on_done, self._on_done = self._on_done, None
            on_done()

    def result(self) -> T:
        self.join()
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]  # set by _run when it did not raise
