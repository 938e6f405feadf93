"""Calls on the kept worker threads: the same value or error as inline, on threads reused call after call."""

from __future__ import annotations

import threading

import pytest

from slam_core.background_call import WORKERS, BackgroundCall


def test_a_background_call_runs_on_a_worker_and_hands_back_its_value() -> None:
    caller = threading.current_thread()
    ran_on: list[threading.Thread] = []
    done_on: list[threading.Thread] = []

    def work() -> int:
        ran_on.append(threading.current_thread())
        return 42

    call = BackgroundCall(work, True, on_done=lambda: done_on.append(threading.current_thread()))
    assert call.result() == 42
    assert call.result() == 42  # collected once, read again
    assert ran_on[0] is not caller
    assert ran_on[0].name.startswith("background-call")
    assert done_on == [caller]  # once, in the caller's thread


def test_inline_when_not_in_the_background() -> None:
    ran_on: list[threading.Thread] = []
    call = BackgroundCall(lambda: ran_on.append(threading.current_thread()) or 7, False)
    assert ran_on == [threading.current_thread()]
    assert call.result() == 7


def test_an_error_is_raised_in_the_caller_and_join_only_waits() -> None:
    def fail() -> int:
        raise ValueError("kernel said no")

    call = BackgroundCall(fail, True)
    call.join()  # does not raise
    with pytest.raises(ValueError, match="kernel said no"):
        call.result()


def test_the_workers_are_kept() -> None:
    threads = {BackgroundCall(threading.current_thread, True).result() for _ in range(50)}
    assert 1 <= len(threads) <= WORKERS
