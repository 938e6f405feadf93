"""What a first start says while the kernels compile: nothing when they load from the cache at once, the
reason and a bar when they take longer."""

from __future__ import annotations

import io
import time

from server.cli.kernel_progress import COMPILING, KernelProgress


def test_a_warm_up_from_the_cache_says_nothing() -> None:
    out = io.StringIO()
    progress = KernelProgress("crowdslam demo", out, quiet_s=0.3)
    for done in range(6):
        progress(done, 5)
    time.sleep(0.5)
    assert out.getvalue() == ""


def test_a_compile_says_so_and_shows_its_steps() -> None:
    out = io.StringIO()
    progress = KernelProgress("crowdslam serve", out, quiet_s=0.05)
    progress(0, 4)
    time.sleep(0.3)
    progress(2, 4)
    progress(4, 4)
    text = out.getvalue()
    assert text.startswith(f"crowdslam serve: {COMPILING}\n")
    assert "about a minute, once" in text
    assert "4/4" in text  # the bar ran to its end
