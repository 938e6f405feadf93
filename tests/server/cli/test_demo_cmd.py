"""``crowdslam demo``, the README's first command: a server on SQLite and crowds walking it, one after
another. A later crowd is new people in the same building, after the earlier one, and is tracked as well
as the first: it walks the same simulated world, later, against the maps the first crowd left."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from server.cli.background_server import CLI, free_port, spawned_processes
from server.simulation.crowd_client import crowd_epoch_ms
from server.store.db import make_engine
from slam_core.sim.simulation import Scenario, simulate
from tests.conftest import TESTBED, write_testbed


def _small_testbed(path: Path) -> Path:
    return write_testbed(path, users=8, walk_length_m=80.0)


def test_crowds_one_after_another_walk_the_same_building(tmp_path: Path) -> None:
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(tmp_path / "data")}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    env.pop("CROWDSLAM_BUILDING_PROCESSES", None)  # the default: processes on more than one core
    scenario = _small_testbed(tmp_path / "small.json")
    args = ["demo", "--crowds", "2", "--speed", "0", "--port", str(free_port()), "--scenario", str(scenario)]
    done = subprocess.run([*CLI, *args], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    assert "sqlite" in out  # the embedded default
    assert "/docs" in out
    assert "/live?token=csk_" in out
    assert re.search(r"phone page:\s+http://127\.0\.0\.1:\d+/phone/#key=csk_\S+&building=demo", out)
    rounds = re.findall(
        r"crowd (\d): (\d+) batches, (\d+) errors, .* error median ([\d.]+) m, p90 ([\d.]+) m", out
    )
    assert [r[0] for r in rounds] == ["0", "1"]
    for _, batches, errors, median, p90 in rounds:
        assert int(batches) > 200
        assert int(errors) == 0
        assert float(median) < 2.5
        assert float(p90) < 7.0
    # measured 1.93 then 1.49 m (a second crowd in another world against the first world's maps: 2.37 m)
    assert float(rounds[1][3]) <= float(rounds[0][3]) + 0.25
    # each crowd left when it had walked: nobody stays on the floor, no device key stays live, and the
    # phones' clocks were the wall clock's, within the demo's lead of a minute
    engine = make_engine(f"sqlite:///{tmp_path / 'data' / 'crowdslam.sqlite3'}")
    try:
        with engine.connect() as connection:
            count = lambda sql: connection.exec_driver_sql(sql).scalar()  # noqa: E731
            assert count("SELECT COUNT(*) FROM latest_positions") == 0
            assert count("SELECT COUNT(*) FROM position_snapshots") == 0
            # the crowds' phones, and the one phone the demo printed a link for
            assert count("SELECT COUNT(*) FROM api_keys WHERE scope = 'device'") == 2 * 8 + 1
            assert count("SELECT COUNT(*) FROM api_keys WHERE scope = 'device' AND revoked_at IS NULL") == 0
            # nor the keys the demo printed: its operator and dashboard keys end with it
            assert count("SELECT COUNT(*) FROM api_keys WHERE scope IN ('operator', 'dashboard')") == 2
            assert count("SELECT COUNT(*) FROM api_keys WHERE revoked_at IS NULL") == 0
            newest_ms = count("SELECT MAX(t_last_ms) FROM batches")
    finally:
        engine.dispose()
    assert abs(newest_ms - time.time() * 1000) < 15 * 60_000


def test_a_world_seed_keeps_the_building_and_changes_the_walks() -> None:
    scenario = Scenario.from_dict(json.loads(TESTBED.read_text()))
    first, second = simulate(scenario, 0, world_seed=0), simulate(scenario, 1, world_seed=0)
    np.testing.assert_array_equal(first.world.anchor_xy, second.world.anchor_xy)
    np.testing.assert_array_equal(first.world.ap_xy, second.world.ap_xy)
    assert not np.array_equal(first.users[0].xy, second.users[0].xy)
    # without a world seed the world follows the seed, as every evaluation has used it
    np.testing.assert_array_equal(simulate(scenario, 0).world.anchor_xy, first.world.anchor_xy)
    assert not np.array_equal(simulate(scenario, 1).world.anchor_xy, first.world.anchor_xy)


def test_a_demo_run_again_in_the_same_folder_moves_a_new_crowd(tmp_path: Path) -> None:
    """Run again in the same folder, the demo had posted the first run's batch ids: 8,830 duplicates and
    nothing moving. Each run's phones are its own."""
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(tmp_path / "data")}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    env.pop("CROWDSLAM_BUILDING_PROCESSES", None)  # the default: processes on more than one core
    scenario = write_testbed(tmp_path / "tiny.json", users=4, walk_length_m=40.0)
    pattern = r"crowd 0: (\d+) batches, (\d+) errors, (\d+) duplicates, .* error median ([\d.]+) m"
    for _ in range(2):
        args = [
            "demo",
            "--crowds",
            "1",
            "--speed",
            "0",
            "--port",
            str(free_port()),
            "--scenario",
            str(scenario),
        ]
        done = subprocess.run([*CLI, *args], env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]
        batches, errors, duplicates, median = re.findall(pattern, done.stdout)[0]
        assert int(batches) > 50
        assert (int(errors), int(duplicates)) == (0, 0)
        assert float(median) < 3.0


def _demo_running_until_stopped(tmp_path: Path, preexec: Callable[[], object]) -> subprocess.Popen[str]:
    """``crowdslam demo`` of a small crowd, forever, in its data folder, with the server's default of building
    processes; ``preexec`` runs in the child before it starts (a process group of its own, say)."""
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(tmp_path / "data")}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    env.pop("CROWDSLAM_BUILDING_PROCESSES", None)  # the default: processes on more than one core
    scenario = _small_testbed(tmp_path / "small.json")
    args = ["demo", "--crowds", "0", "--speed", "5", "--port", str(free_port()), "--scenario", str(scenario)]
    return subprocess.Popen(
        [*CLI, *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=preexec,
    )


@pytest.mark.parametrize(
    ("signum", "to_group"),
    [(signal.SIGINT, False), (signal.SIGTERM, False), (signal.SIGINT, True)],
    ids=["sigint-in-the-background", "sigterm", "ctrl-c-in-a-terminal"],
)
def test_the_demo_stops_cleanly_on_sigint_and_sigterm_even_in_the_background(
    tmp_path: Path, signum: int, to_group: bool
) -> None:
    """Started in the background (SIGINT ignored, as a shell's `&` leaves it), the demo had ignored Ctrl-C
    and died on SIGTERM without a snapshot. Both now stop it, and the final snapshot covers every batch
    (no logged body is left to replay). Ctrl-C in a terminal reaches the whole process group, the building's
    process too, which had died with a traceback in the middle of a transaction: children leave it to the
    demo, which stops them in order."""
    # a terminal's foreground process group of its own, or a shell's `&` (SIGINT ignored)
    process = _demo_running_until_stopped(
        tmp_path, os.setpgrp if to_group else lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)
    )
    try:
        assert process.stdout is not None
        for line in process.stdout:
            if "Ctrl-C stops." in line:
                break
        time.sleep(3)  # the crowd is walking
        if to_group:
            os.killpg(process.pid, signum)
        else:
            process.send_signal(signum)
        rest, _ = process.communicate(timeout=120)  # read while waiting: a full pipe would hold it
        assert process.returncode == 0, rest
        assert "Traceback" not in rest, rest
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()
    engine = make_engine(f"sqlite:///{tmp_path / 'data' / 'crowdslam.sqlite3'}")
    try:
        with engine.connect() as connection:
            logged = connection.exec_driver_sql("SELECT COUNT(*) FROM batch_log").scalar()
            accepted = connection.exec_driver_sql("SELECT COUNT(*) FROM batches").scalar()
            snapshots = connection.exec_driver_sql("SELECT COUNT(*) FROM tracker_snapshots").scalar()
    finally:
        engine.dispose()
    assert accepted is not None
    assert accepted > 0
    assert snapshots == 1
    assert logged == 0


@pytest.mark.parametrize("when", ["importing", "spawning"])
def test_ctrl_c_while_the_demo_starts_prints_no_traceback_and_leaves_no_process(
    tmp_path: Path, when: str
) -> None:
    """Ctrl-C in a terminal reaches the whole process group: the demo still importing (an extension module
    interrupted in its start raises an ImportError caused by the interrupt), or its first children just
    spawned (the kernels' compile, importing numba), which had each printed a KeyboardInterrupt traceback.
    Children are started with Ctrl-C blocked and die with the demo."""
    process = _demo_running_until_stopped(tmp_path, os.setpgrp)
    try:
        if when == "importing":
            time.sleep(0.3)
        else:
            deadline = time.monotonic() + 60.0
            while not spawned_processes(tmp_path / "data") and time.monotonic() < deadline:
                time.sleep(0.02)
            assert spawned_processes(tmp_path / "data"), "the demo spawned no process"
        os.killpg(process.pid, signal.SIGINT)
        out, _ = process.communicate(timeout=120)  # read while waiting: a full pipe would hold it
        assert process.returncode in (0, 130), out
        assert "Traceback" not in out, out
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()
    deadline = time.monotonic() + 10.0
    while spawned_processes(tmp_path / "data") and time.monotonic() < deadline:
        time.sleep(0.1)
    assert spawned_processes(tmp_path / "data") == []


def test_a_crowds_clock_runs_at_most_a_minute_ahead_of_the_wall_clock() -> None:
    now = 1_800_000_000_000
    assert crowd_epoch_ms(now, 200.0, 1.0) == now  # in real time a crowd starts now and stays level
    assert crowd_epoch_ms(now, 200.0, 5.0) == now - 100_000  # it gains 160 s, 60 s of which it may
    assert crowd_epoch_ms(now, 200.0, 0.0) == now - 140_000  # flat out it gains all 200 s
    assert crowd_epoch_ms(now, 50.0, 5.0) == now


def test_the_phone_link_is_a_qr_code_only_where_a_phone_can_open_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A phone opens the demo's page over HTTPS on the network: there the link comes with its QR code; on
    loopback or plain HTTP the demo says how to get one instead."""
    from server.cli.demo_cmd import print_phone_link
    from server.tls import self_signed

    tls = self_signed(tmp_path / "tls", ["192.168.1.20"])
    print_phone_link("127.0.0.1", 8000, None, "csk_ab_cd", "demo")
    out = capsys.readouterr().out
    assert "phone page:          http://127.0.0.1:8000/phone/#key=csk_ab_cd&building=demo" in out
    assert "crowdslam demo --host 0.0.0.0 --tls-self-signed" in out
    assert not set("\u2588\u2580\u2584") & set(out)  # no code: a phone cannot open that address

    print_phone_link("0.0.0.0", 8443, tls, "csk_ab_cd", "demo")
    out = capsys.readouterr().out
    link = re.search(r"phone page:\s+(\S+)", out)
    assert link is not None
    assert re.fullmatch(r"https://[\d.]+:8443/phone/#key=csk_ab_cd&building=demo", link.group(1))
    assert "0.0.0.0" not in link.group(1)  # the machine's address on its network, which a phone can reach
    code_rows = [
        line for line in out.splitlines() if "\u2588" in line or "\u2580" in line or "\u2584" in line
    ]
    assert len(code_rows) >= 12  # the QR code, two modules a line
