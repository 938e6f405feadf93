"""Settings whose default depends on the machine: building processes where there is more than one core."""

from __future__ import annotations

from pathlib import Path

import pytest

from server import settings as settings_module
from server.settings import Settings


@pytest.mark.parametrize(("cores", "processes"), [(1, False), (2, True), (16, True)])
def test_buildings_get_processes_of_their_own_where_there_is_more_than_one_core(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cores: int, processes: bool
) -> None:
    monkeypatch.delenv("CROWDSLAM_BUILDING_PROCESSES", raising=False)
    monkeypatch.setattr(settings_module.os, "sched_getaffinity", lambda pid: set(range(cores)))
    assert Settings(data_dir=tmp_path).resolved_building_processes is processes
    # said outright, it holds whatever the machine
    assert Settings(data_dir=tmp_path, building_processes=False).resolved_building_processes is False
    monkeypatch.setenv("CROWDSLAM_BUILDING_PROCESSES", "true")
    assert Settings(data_dir=tmp_path).resolved_building_processes is True


def test_the_cores_counted_are_those_this_process_may_use() -> None:
    assert settings_module.usable_cores() == len(settings_module.os.sched_getaffinity(0))


def test_a_cluster_role_needs_nats_and_postgresql(tmp_path: Path) -> None:
    assert Settings(data_dir=tmp_path).cluster_problem() is None  # the embedded default needs neither
    pg = "postgresql+psycopg://crowdslam@db/crowdslam"
    for role in ("front", "worker"):
        problem = Settings(data_dir=tmp_path, role=role, database_url=pg).cluster_problem()
        assert problem is not None
        assert "CROWDSLAM_NATS_URL" in problem
        problem = Settings(data_dir=tmp_path, role=role, nats_url="nats://n:4222").cluster_problem()
        assert problem is not None
        assert "PostgreSQL" in problem  # SQLite is one process's database
        assert (
            Settings(data_dir=tmp_path, role=role, nats_url="nats://n", database_url=pg).cluster_problem()
            is None
        )
