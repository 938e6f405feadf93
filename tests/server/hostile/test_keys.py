"""Keys can be listed (never their secrets), with their last use, and revoked by prefix: through the API for
a building's keys, and from the command line for site-wide ones. A key revoked in this server is refused
from its next request; elsewhere within the key cache's lifetime."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.server.api.test_api import _batch
from tests.server.conftest import Api, migrate_with_operator


def test_a_buildings_keys_are_listed_and_revoked(api: Api) -> None:
    api.create_building()
    device = api.key("hq", "device", "phone-1")
    dashboard = api.key("hq", "dashboard")
    op = api.auth(api.operator)
    listed = api.client.get("/v1/buildings/hq/keys", headers=op)
    assert listed.status_code == 200, listed.text
    keys = {k["prefix"]: k for k in listed.json()}
    assert {k["scope"] for k in keys.values()} == {"device", "dashboard"}
    assert all("key" not in k and "key_hash" not in k for k in keys.values())
    assert not any(device in str(k) or dashboard in str(k) for k in keys.values())
    device_prefix = device.split("_")[1]
    assert keys[device_prefix]["device_id"] == "phone-1"
    assert keys[device_prefix]["last_used_at"] is None

    response = api.client.post("/v1/buildings/hq/batches", json=_batch(0), headers=api.auth(device))
    assert response.status_code == 200
    used = {k["prefix"]: k for k in api.client.get("/v1/buildings/hq/keys", headers=op).json()}
    assert used[device_prefix]["last_used_at"] is not None

    # a dashboard key reads positions but cannot list or revoke keys
    assert api.client.get("/v1/buildings/hq/keys", headers=api.auth(dashboard)).status_code == 403
    assert (
        api.client.delete(f"/v1/buildings/hq/keys/{device_prefix}", headers=api.auth(dashboard)).status_code
        == 403
    )

    assert api.client.delete(f"/v1/buildings/hq/keys/{device_prefix}", headers=op).status_code == 204
    refused = api.client.post("/v1/buildings/hq/batches", json=_batch(1), headers=api.auth(device))
    assert refused.status_code == 401  # at once, though the key was cached a moment ago
    after = {k["prefix"]: k for k in api.client.get("/v1/buildings/hq/keys", headers=op).json()}
    assert after[device_prefix]["revoked_at"] is not None
    assert api.client.delete(f"/v1/buildings/hq/keys/{device_prefix}", headers=op).status_code == 404
    assert api.client.get("/v1/buildings/nowhere/keys", headers=op).status_code == 404


def test_site_wide_keys_from_the_command_line(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    prefix = operator.split("_")[1]
    env = {**os.environ, "CROWDSLAM_DATABASE_URL": url, "CROWDSLAM_DATA_DIR": str(tmp_path)}
    cli = [sys.executable, "-c", "import sys; from server.cli.main import main; sys.exit(main(sys.argv[1:]))"]

    def run(*argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*cli, *argv], capture_output=True, text=True, env=env, timeout=120)

    listed = run("keys", "list")
    assert listed.returncode == 0, listed.stderr
    assert prefix in listed.stdout
    assert "live" in listed.stdout
    assert operator not in listed.stdout
    revoked = run("keys", "revoke", prefix)
    assert revoked.returncode == 0, revoked.stderr
    assert "revoked" in run("keys", "list").stdout
    again = run("keys", "revoke", prefix)
    assert again.returncode == 2
    assert "no live key" in again.stderr
