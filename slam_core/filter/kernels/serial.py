"""Serial twins of the batch kernels, for calls too small to be worth a parallel region.

A ``parallel=True`` kernel hands its ``prange`` to numba's thread pool. When the machine's other core is
busy (on the server: the HTTP front, the phones' sockets), waking the pool costs more than the work of a few
dozen users, and its tail is long while the parallel region waits for its second thread to be scheduled
(``python bench/kernel_dispatch.py`` measures it). The server's building applies a group
of some tens of phones per call, so its kernels run serially; a call over many users (a benchmark tick, a
crowd-map merge over a whole building) still runs in parallel.

A twin is the same Python function compiled without ``parallel=True`` (``prange`` then runs as ``range``),
under a name of its own so that numba's on-disk cache keeps the two compilations apart. Both give the same
numbers: every draw comes from the user's own counter-based stream, whatever the loop's order.
"""

from __future__ import annotations

import types
from typing import Any

from numba import njit

PARALLEL_MIN_USERS = 256
"""Users per call from which a kernel runs in parallel: at 128 users the parallel summary was 1.8x faster
on an idle machine but slower on average with the other core busy."""


def serial_twin(kernel: Any) -> Any:
    """``kernel`` (an ``@njit(parallel=True)`` dispatcher) compiled serially: ``cache=True, nogil=True``."""
    f = kernel.py_func
    name = f.__name__ + "_serial"
    twin = types.FunctionType(f.__code__, f.__globals__, name, f.__defaults__, f.__closure__)
    twin.__qualname__ = f.__qualname__ + "_serial"  # numba names its cache files after the qualified name
    twin.__module__ = f.__module__
    twin.__doc__ = f"Serial twin of ``{f.__name__}`` (``slam_core.filter.kernels.serial``)."
    return njit(cache=True, nogil=True)(twin)


def pick(kernel: Any, twin: Any, n_users: int, parallel_min_users: int) -> Any:
    """The parallel kernel for ``n_users`` >= ``parallel_min_users``, else its serial twin."""
    return kernel if n_users >= parallel_min_users else twin
