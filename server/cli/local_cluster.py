"""A cluster on this machine, one process at a time: a private NATS server with JetStream, a new PostgreSQL
database, fronts (``crowdslam serve --role front``) and workers (``--role worker``). The cluster's tests and
``bench/load.py --cluster`` start theirs with it."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

from sqlalchemy import make_url

from server.cli.background_server import CLI, ServerDidNotStartError, wait_until_ready
from server.store.db import make_engine


def nats_server(port: int, store: Path, log: Path, start_timeout_s: float = 20.0) -> subprocess.Popen[bytes]:
    """``nats-server -js`` on 127.0.0.1:``port``, its streams kept in ``store`` (a restart finds them);
    returns once it accepts connections."""
    binary = shutil.which("nats-server")
    if binary is None:
        raise ServerDidNotStartError(
            "nats-server is not on PATH (https://docs.nats.io/running-a-nats-service)"
        )
    with log.open("ab") as sink:
        process = subprocess.Popen(
            [binary, "-js", "-a", "127.0.0.1", "-p", str(port), "-sd", str(store)],
            stdout=sink,
            stderr=subprocess.STDOUT,
        )

    def accepts() -> bool:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
        return False

    return wait_until_ready(process, "nats-server", log, accepts, start_timeout_s)


READY = b"serving buildings"
"""What a worker logs once its kernels are warm and it is about to take buildings."""


def worker_process(
    env: Mapping[str, str], log: Path, start_timeout_s: float = 300.0
) -> subprocess.Popen[bytes]:
    """``crowdslam serve --role worker`` (output appended to ``log``); returns once it is ready to take
    buildings (a first start compiles the kernels), which its log says at level info (a worker logs little
    more: buildings taken, handed off, lost). The caller stops it (SIGTERM hands its buildings off;
    SIGKILL to test failover)."""
    offset = log.stat().st_size if log.exists() else 0
    with log.open("ab") as sink:
        process = subprocess.Popen(
            [*CLI, "serve", "--role", "worker", "--log-level", "info"],
            env={**env, "CROWDSLAM_ROLE": "worker"},
            stdout=sink,
            stderr=subprocess.STDOUT,
        )

    def logged_ready() -> bool:
        return READY in log.read_bytes()[offset:]

    return wait_until_ready(process, "the worker", log, logged_ready, start_timeout_s)


@contextlib.contextmanager
def postgres_database(server_url: str, prefix: str = "crowdslam") -> Iterator[str]:
    """A new database on the PostgreSQL server at ``server_url`` (whose databases the caller may create and
    drop), dropped on exit; yields its URL."""
    name = f"{prefix}_{os.getpid()}_{time.monotonic_ns()}"
    admin = make_engine(server_url, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            conn.exec_driver_sql(f'CREATE DATABASE "{name}"')
        yield make_url(server_url).set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as conn:
            conn.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.dispose()
