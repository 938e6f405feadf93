"""How much disk the server takes and has left: the data directory (recordings, signal maps, the embedded
database), the database, and the free space of the data directory's disk. Exposed as metrics and in
``/healthz``, so that an operator hears of a filling disk before it stops the batches."""

from __future__ import annotations

import os
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import Engine, text

SIZES_MAX_AGE_S = 60.0
"""The sizes are measured again at most this often: a walk of the data directory is not free."""


@dataclass(frozen=True)
class Storage:
    data_dir_bytes: int
    """Everything under the data directory (the embedded SQLite database included)."""
    database_bytes: int
    """The database: SQLite's file and its write-ahead log, or PostgreSQL's ``pg_database_size``."""
    free_bytes: int
    """Free space on the data directory's disk, for this process's user."""


def free_bytes(data_dir: Path) -> int:
    """Free space on the disk that holds ``data_dir`` (or its nearest existing parent)."""
    path = data_dir
    while not path.exists() and path != path.parent:
        path = path.parent
    return int(shutil.disk_usage(path).free)


def tree_bytes(root: Path) -> int:
    """Bytes of the files under ``root`` (files that vanish during the walk are passed over)."""
    total = 0
    for folder, _, files in os.walk(root):
        for name in files:
            try:
                total += os.stat(os.path.join(folder, name), follow_symlinks=False).st_size
            except OSError:
                continue
    return total


def database_bytes(engine: Engine) -> int:
    if engine.dialect.name == "sqlite":
        database = engine.url.database
        if not database or database == ":memory:":
            return 0
        return sum(
            Path(database + suffix).stat().st_size
            for suffix in ("", "-wal", "-shm")
            if Path(database + suffix).exists()
        )
    with engine.connect() as connection:
        return int(connection.execute(text("SELECT pg_database_size(current_database())")).scalar_one())


class StorageWatch:
    """The figures of ``Storage``, the sizes measured again at most every ``SIZES_MAX_AGE_S`` (the free space
    every time: one system call). Thread-safe: metrics are rendered off the event loop."""

    def __init__(self, data_dir: Path, engine: Engine) -> None:
        self.data_dir = data_dir
        self.engine = engine
        self._lock = threading.Lock()
        self._sizes: tuple[float, int, int] | None = None

    def storage(self) -> Storage:
        with self._lock:
            now = time.monotonic()
            if self._sizes is None or now - self._sizes[0] > SIZES_MAX_AGE_S:
                self._sizes = (now, tree_bytes(self.data_dir), database_bytes(self.engine))
            _, data_dir, database = self._sizes
        return Storage(data_dir, database, free_bytes(self.data_dir))
