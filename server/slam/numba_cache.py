"""Where numba keeps compiled kernels.

numba's on-disk cache is keyed by each file's own timestamp, so after a change to a kernel helper that
others inline (the random numbers, the 2x2 algebra), their cached machine code goes stale silently. The
cache directory is therefore keyed by a hash of every kernel source file.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path


def kernel_sources() -> Path:
    """Where the ``slam_core`` package is, found without importing it (nor numba)."""
    spec = importlib.util.find_spec("slam_core")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("the slam_core package cannot be found: is crowdslam installed?")
    return Path(next(iter(spec.submodule_search_locations)))


def kernel_source_hash(root: Path | None = None) -> str:
    """A hash of every source file of ``slam_core`` (``root``: that package's folder)."""
    root = root or kernel_sources()
    sources = sorted(root.rglob("*.py"))
    if not sources:
        raise RuntimeError(f"no kernel sources under {root}")
    digest = hashlib.sha256()
    for path in sources:
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def configure_numba_cache(base: Path | None = None) -> Path:
    """Point NUMBA_CACHE_DIR at ``base/<hash of the kernel sources>`` unless the environment already set it.
    Must run before numba is imported."""
    if "NUMBA_CACHE_DIR" in os.environ:
        return Path(os.environ["NUMBA_CACHE_DIR"])
    root = base or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "crowdslam" / "numba"
    path = root / kernel_source_hash()
    path.mkdir(parents=True, exist_ok=True)
    os.environ["NUMBA_CACHE_DIR"] = str(path)
    return path
