"""Where numba keeps compiled kernels.

numba's on-disk cache is keyed by each file's own timestamp, so after a change to a kernel helper that
others inline (the random numbers, the 2x2 algebra), their cached machine code goes stale silently. The
cache directory is therefore keyed by a hash of every kernel source file.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

KERNELS = Path(__file__).resolve().parents[1] / "slam_core"


def kernel_source_hash() -> str:
    digest = hashlib.sha256()
    for path in sorted(KERNELS.rglob("*.py")):
        digest.update(path.relative_to(KERNELS).as_posix().encode())
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
