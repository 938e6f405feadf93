"""What a first start says while the kernels compile: nothing when they load from the cache at once, the
reason and a bar when they take longer."""

from __future__ import annotations

import io
import time
from pathlib import Path

import pytest

from server.cli.kernel_progress import COMPILING, LOADING, WARM_QUIET_S, KernelProgress, kernels_cached


def test_a_warm_up_from_the_cache_says_nothing() -> None:
    out = io.StringIO()
    progress = KernelProgress("crowdslam demo", out, quiet_s=0.3, cached=False)
    for done in range(6):
        progress(done, 5)
    time.sleep(0.5)
    assert out.getvalue() == ""


def test_a_compile_says_so_and_shows_its_steps() -> None:
    out = io.StringIO()
    progress = KernelProgress("crowdslam serve", out, quiet_s=0.05, cached=False)
    progress(0, 4)
    time.sleep(0.3)
    progress(2, 4)
    progress(4, 4)
    text = out.getvalue()
    assert text.startswith(f"crowdslam serve: {COMPILING}\n")
    assert "about a minute, once" in text
    assert "4/4" in text  # the bar ran to its end


def test_a_warm_start_of_a_few_seconds_says_nothing_of_compiling() -> None:
    """From a warm cache the warm-up still runs its crowd (seconds): that is no compile, and says nothing."""
    out = io.StringIO()
    progress = KernelProgress("crowdslam serve", out, quiet_s=0.05, cached=True)
    assert progress.quiet_s == WARM_QUIET_S
    progress(0, 4)
    time.sleep(0.3)
    progress(4, 4)
    assert out.getvalue() == ""


def test_a_warm_start_that_takes_long_says_it_is_loading() -> None:
    out = io.StringIO()
    progress = KernelProgress("crowdslam serve", out, cached=True)
    progress.quiet_s = 0.05
    progress(0, 4)
    time.sleep(0.3)
    progress(4, 4)
    assert out.getvalue().startswith(f"crowdslam serve: {LOADING}\n")
    assert COMPILING not in out.getvalue()


def test_a_cache_folder_without_kernels_is_a_first_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert not kernels_cached()
    (tmp_path / "slam_core" / "filter").mkdir(parents=True)
    (tmp_path / "slam_core" / "filter" / "motion.step-1.py311.nbi").write_bytes(b"x")
    assert kernels_cached()
