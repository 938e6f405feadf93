"""The compose file starts the cluster the README describes: NATS with JetStream, PostgreSQL, migrations
first, two workers and two fronts on the same database and NATS, one address in front of the fronts."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from server.settings import Settings

DOCKER = Path(__file__).resolve().parents[3] / "docker"


def _compose() -> dict[str, Any]:
    loaded: dict[str, Any] = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    return loaded


def test_the_compose_file_runs_two_fronts_and_two_workers_on_nats_and_postgresql() -> None:
    services = _compose()["services"]
    assert "-js" in services["nats"]["command"]
    roles: dict[str, list[str]] = {"front": [], "worker": []}
    for name, service in services.items():
        command = service.get("command", [])
        if "--role" not in command:
            continue
        role = command[command.index("--role") + 1]
        roles[role].append(name)
        env = service["environment"]
        # what a cluster process refuses to start without
        settings = Settings(
            role=role, database_url=env["CROWDSLAM_DATABASE_URL"], nats_url=env["CROWDSLAM_NATS_URL"]
        )
        assert settings.cluster_problem() is None, name
        assert "@nats:4222" in env["CROWDSLAM_NATS_URL"]
        assert "@db:5432/" in env["CROWDSLAM_DATABASE_URL"]
        assert service["depends_on"]["migrate"]["condition"] == "service_completed_successfully"
        assert "data:/data" in service["volumes"]  # a building's recordings follow it between workers
    assert sorted(roles["front"]) == ["front-1", "front-2"]
    assert sorted(roles["worker"]) == ["worker-1", "worker-2"]
    assert services["migrate"]["command"] == ["crowdslam", "migrate"]
    upstream = (DOCKER / "nginx.conf").read_text()
    assert "server front-1:8000" in upstream
    assert "server front-2:8000" in upstream
    assert "8000:8000" in services["proxy"]["ports"]
