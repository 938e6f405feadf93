"""A user's mistake on the command line is one line on stderr and exit code 2, with no traceback."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import SHARED

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
    raw = json.loads((SHARED / "scenarios" / "paper-testbed.json").read_text())
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
