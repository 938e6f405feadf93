"""``crowdslam serve``: a cluster role without what it needs, or a setting this version no longer reads,
stops it at once and says what is missing or what replaced it."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from server.cli.background_server import CLI


@pytest.mark.parametrize("role", ["front", "worker"])
def test_a_cluster_role_without_nats_or_postgresql_says_what_it_needs(tmp_path: Path, role: str) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CROWDSLAM_")}
    env["CROWDSLAM_DATA_DIR"] = str(tmp_path)
    done = subprocess.run(
        [*CLI, "serve", "--role", role], env=env, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 1
    assert "needs CROWDSLAM_NATS_URL" in done.stderr
    done = subprocess.run(
        [*CLI, "serve", "--role", role, "--nats", "nats://127.0.0.1:4222"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 1
    assert "needs PostgreSQL" in done.stderr  # SQLite is one process's database


def test_a_retired_setting_stops_the_server_and_names_its_successor(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CROWDSLAM_")}
    env |= {"CROWDSLAM_DATA_DIR": str(tmp_path), "CROWDSLAM_BATCH_IDS_DAYS": "2"}
    done = subprocess.run([*CLI, "serve"], env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert "CROWDSLAM_BATCH_IDS_DAYS is no longer read: set CROWDSLAM_BATCH_IDS_HOURS" in done.stderr
