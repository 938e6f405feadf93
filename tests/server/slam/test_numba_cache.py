"""The numba cache folder is named after the kernels' sources: a change to any of them is a new folder."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from server.slam import numba_cache
from tests.conftest import ROOT


def test_the_sources_are_the_slam_core_package() -> None:
    assert numba_cache.kernel_sources().resolve() == (ROOT / "slam_core").resolve()


def test_a_change_to_any_kernel_source_is_another_cache_folder(tmp_path: Path) -> None:
    copy = tmp_path / "slam_core"
    shutil.copytree(ROOT / "slam_core", copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = numba_cache.kernel_source_hash(copy)
    assert before == numba_cache.kernel_source_hash()
    helper = copy / "filter" / "kernels" / "rng.py"
    helper.write_text(helper.read_text() + "\n# changed\n")
    assert numba_cache.kernel_source_hash(copy) != before


def test_no_sources_is_an_error_not_a_hash_of_nothing(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="no kernel sources"):
        numba_cache.kernel_source_hash(tmp_path)


def test_the_folder_is_keyed_by_the_hash(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    path = numba_cache.configure_numba_cache(tmp_path)
    assert path == tmp_path / numba_cache.kernel_source_hash()
    assert path.is_dir()
    assert os.environ["NUMBA_CACHE_DIR"] == str(path)
