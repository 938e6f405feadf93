"""A user's mistake on the command line is one line on stderr and exit code 2, with no traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import TESTBED

CLI = [sys.executable, "-c", "import sys; from server.cli.main import main; sys.exit(main(sys.argv[1:]))"]


def _run(*argv: str, cwd: Path) -> tuple[int, str, str]:
    done = subprocess.run([*CLI, *argv], capture_output=True, text=True, cwd=cwd, timeout=120)
    return done.returncode, done.stdout, done.stderr


def _one_line(code: int, stderr: str) -> str:
    assert code == 2, stderr
    assert "Traceback" not in stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    return lines[0]


@pytest.fixture
def scenario(tmp_path: Path) -> Path:
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = 2
    path = tmp_path / "small.json"
    path.write_text(json.dumps(raw))
    return path


def test_simulate_with_bad_files_and_servers(tmp_path: Path, scenario: Path) -> None:
    base = ["simulate", "--building", "hq", "--key", "k"]
    code, _, err = _run(
        *base, "--scenario", str(tmp_path / "missing.json"), "--post", "http://x", cwd=tmp_path
    )
    assert "missing.json" in _one_line(code, err)
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    code, _, err = _run(*base, "--scenario", str(bad), "--post", "http://x", cwd=tmp_path)
    assert "not valid JSON" in _one_line(code, err)
    odd = tmp_path / "odd.json"
    odd.write_text('{"name": "x"}')
    code, _, err = _run(*base, "--scenario", str(odd), "--post", "http://x", cwd=tmp_path)
    assert "not a usable scenario" in _one_line(code, err)
    code, _, err = _run(*base, "--scenario", str(scenario), "--post", "http://127.0.0.1:9", cwd=tmp_path)
    assert "cannot reach the server" in _one_line(code, err)
    code, _, err = _run(*base, "--scenario", str(scenario), "--post", "127.0.0.1:8000", cwd=tmp_path)
    assert "not a usable URL" in _one_line(code, err)


def test_migrate_with_bad_urls(tmp_path: Path) -> None:
    code, _, err = _run("migrate", "--database-url", "not a url", cwd=tmp_path)
    assert "not a database URL" in _one_line(code, err)
    unreachable = "postgresql+psycopg://nobody@127.0.0.1:9/nowhere"
    code, _, err = _run("migrate", "--database-url", unreachable, cwd=tmp_path)
    assert "cannot reach the database" in _one_line(code, err)


def test_replay_of_a_file_that_is_not_a_recording(tmp_path: Path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    code, out, err = _run("replay", str(text), "--offline", cwd=tmp_path)
    assert "is not an MCAP recording" in _one_line(code, err)
    assert "batches" not in out
    code, _, err = _run("replay", str(tmp_path / "gone.mcap"), "--offline", cwd=tmp_path)
    assert "gone.mcap" in _one_line(code, err)


def test_ports_out_of_range_and_unknown_options(tmp_path: Path) -> None:
    code, _, err = _run("serve", "--port", "99999", cwd=tmp_path)
    assert "out of range" in _one_line(code, err)
    code, _, err = _run("demo", "--port", "-1", cwd=tmp_path)
    assert "out of range" in _one_line(code, err)
    code, _, err = _run("serve", "--no-such-option", cwd=tmp_path)
    assert "unrecognized arguments" in _one_line(code, err)


def test_no_command_lists_the_commands(tmp_path: Path) -> None:
    code, out, err = _run(cwd=tmp_path)
    assert code == 0, err
    for command in ("demo", "serve", "evaluate", "datasets", "replay"):
        assert f"    {command}" in out


def test_a_folder_that_is_not_a_floor_answers_before_any_work(tmp_path: Path) -> None:
    """No progress bar starts before the error: the folder is checked as the arguments are read."""
    out = str(tmp_path / "x.json")
    for argv in (
        ("evaluate", "--msindoor", str(tmp_path / "nowhere"), "--json", out),
        ("signalslam", "--msindoor", str(tmp_path / "nowhere"), "--json", out),
        ("calibrate", "--msindoor", str(tmp_path / "nowhere"), "--out", out),
        ("import-msindoor", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x.mcap")),
    ):
        code, _, err = _run(*argv, cwd=tmp_path)
        line = _one_line(code, err)
        assert "nowhere: no such folder" in line
        assert "crowdslam datasets fetch msindoor20" in line
    code, _, err = _run("evaluate", "--msindoor", str(tmp_path), "--json", out, cwd=tmp_path)
    assert "is neither a floor of Indoor Location 2.0 walks" in _one_line(code, err)
    (tmp_path / "notes.txt").write_text("a shopping list\n")
    code, _, err = _run("import-msindoor", str(tmp_path), "--out", str(tmp_path / "x.mcap"), cwd=tmp_path)
    assert "notes.txt is not an Indoor Location 2.0 walk" in _one_line(code, err)
    assert not (tmp_path / "x.mcap").exists()
    assert not (tmp_path / "x.json").exists()


def test_an_unknown_key_prefix_and_scenario(tmp_path: Path) -> None:
    env_dir = ["--database-url", f"sqlite:///{tmp_path / 'db.sqlite3'}"]
    assert _run("migrate", *env_dir, cwd=tmp_path)[0] == 0
    done = subprocess.run(
        [*CLI, "keys", "revoke", "0a1b2c3d"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
        env={**os.environ, "CROWDSLAM_DATABASE_URL": f"sqlite:///{tmp_path / 'db.sqlite3'}"},
    )
    assert "no live key '0a1b2c3d'" in _one_line(done.returncode, done.stderr)
    code, _, err = _run("evaluate", "--scenario", "paper-testbd", "--json", "x.json", cwd=tmp_path)
    assert "nor a shipped scenario (paper-testbed, three-floors)" in _one_line(code, err)
    code, _, err = _run("datasets", "fetch", "msindoor20", "--floors", "site9/F1", cwd=tmp_path)
    assert "has no floor site9/F1; its floors: site1/F1" in _one_line(code, err)


@pytest.mark.parametrize(
    ("command", "variable", "value", "said"),
    [
        (
            "migrate",
            "CROWDSLAM_DATABASE_URL",
            "mysql://root@localhost/test",
            "SQLite (the default) or PostgreSQL",
        ),
        ("serve", "CROWDSLAM_DATABASE_URL", "mysql+pymysql://root@localhost/test", "PostgreSQL"),
        ("migrate", "CROWDSLAM_MODE", "magic", "'dynamicslam' or 'semanticslam'"),
        ("demo", "CROWDSLAM_MODE", "magic", "(got 'magic')"),
        ("serve", "CROWDSLAM_SNAPSHOT_PERIOD_S", "soon", "CROWDSLAM_SNAPSHOT_PERIOD_S"),
    ],
)
def test_a_setting_the_server_cannot_use_is_one_line_naming_it(
    tmp_path: Path, command: str, variable: str, value: str, said: str
) -> None:
    env = {**os.environ, variable: value, "CROWDSLAM_DATA_DIR": str(tmp_path)}
    done = subprocess.run([*CLI, command], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
    line = _one_line(done.returncode, done.stderr)
    assert line.startswith(f"crowdslam {command}: configuration: {variable}: "), line
    assert said in line
