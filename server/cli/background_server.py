"""Run the app under uvicorn in a background thread, or ``crowdslam serve`` in its own process (the demo,
end-to-end and crash tests, benchmarks)."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import httpx
import uvicorn
from fastapi import FastAPI

from server.tls import TlsFiles

CLI = [sys.executable, "-c", "import sys; from server.cli.main import main; sys.exit(main(sys.argv[1:]))"]
"""``crowdslam`` run by this interpreter, whether or not the console script is on PATH."""


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class ServerDidNotStartError(RuntimeError):
    pass


def wait_until_ready(
    process: subprocess.Popen[bytes],
    name: str,
    log: Path,
    ready: Callable[[], bool],
    timeout_s: float,
    poll_s: float = 0.1,
) -> subprocess.Popen[bytes]:
    """``process`` once ``ready()`` says so. ``ServerDidNotStartError`` with its log if it exits first;
    killed, and the same error, if it is not ready within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise ServerDidNotStartError(f"{name} exited with {process.returncode}:\n{log.read_text()}")
        if ready():
            return process
        time.sleep(poll_s)
    process.kill()
    process.wait()
    raise ServerDidNotStartError(f"{name} was not ready within {timeout_s:.0f} s")


@contextmanager
def running_server(
    app: FastAPI,
    host: str,
    port: int,
    start_timeout_s: float = 120.0,
    ws_compression: bool = False,
    tls: TlsFiles | None = None,
) -> Iterator[str]:
    """Start serving ``app`` (``port`` 0: a free one; HTTPS with ``tls``); yields its base URL once it accepts
    connections, stops it on exit."""
    port = port or free_port(host)
    config = uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level="warning",
        ws="websockets-sansio",
        ws_per_message_deflate=ws_compression,
        ws_max_size=app.state.settings.max_ws_frame_bytes,
        ssl_certfile=None if tls is None else str(tls.cert),
        ssl_keyfile=None if tls is None else str(tls.key),
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + start_timeout_s
    while not server.started:
        if not thread.is_alive():
            raise ServerDidNotStartError(f"the server did not start on {host}:{port} (is the port free?)")
        if time.monotonic() > deadline:
            server.should_exit = True
            raise ServerDidNotStartError(f"the server did not start within {start_timeout_s:.0f} s")
        time.sleep(0.05)
    try:
        yield f"{'http' if tls is None else 'https'}://{host}:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=120)  # the lifespan's shutdown snapshots every building


def migrate_with_operator_key(env: Mapping[str, str]) -> str:
    """``crowdslam migrate`` and ``crowdslam keys create --scope operator`` on the database ``env`` names, as
    an operator sets up a server; returns the operator key."""
    subprocess.run([*CLI, "migrate"], env=dict(env), check=True, capture_output=True)
    created = subprocess.run(
        [*CLI, "keys", "create", "--scope", "operator"],
        env=dict(env),
        check=True,
        capture_output=True,
        text=True,
    )
    return created.stdout.strip().splitlines()[-1]


def serve_process(
    env: Mapping[str, str],
    port: int,
    log: Path,
    host: str = "127.0.0.1",
    log_level: str = "info",
    start_timeout_s: float = 120.0,
) -> subprocess.Popen[bytes]:
    """Start ``crowdslam serve`` in its own process (output appended to ``log``); returns once /healthz
    answers. The caller stops it (terminate, or SIGKILL to test crash recovery)."""
    with log.open("ab") as sink:
        process = subprocess.Popen(
            [*CLI, "serve", "--host", host, "--port", str(port), "--log-level", log_level],
            env=dict(env),
            stdout=sink,
            stderr=subprocess.STDOUT,
        )

    def answers() -> bool:
        try:
            return httpx.get(f"http://{host}:{port}/healthz", timeout=1.0).status_code == 200
        except httpx.TransportError:
            return False

    return wait_until_ready(process, "crowdslam serve", log, answers, start_timeout_s, poll_s=0.2)


def spawned_processes(data_dir: Path) -> list[int]:
    """The processes a server of this data directory spawned that are still alive: its buildings', its
    kernels' compile, its signal-map builds' (Linux ``/proc``)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            cmdline = (entry / "cmdline").read_bytes()
            environ = (entry / "environ").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmdline and f"CROWDSLAM_DATA_DIR={data_dir}".encode() in environ.split(b"\0"):
            found.append(int(entry.name))
    return found
