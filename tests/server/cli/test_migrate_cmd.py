from __future__ import annotations

from pathlib import Path

import pytest

from server.cli.main import main
from server.store.db import make_engine
from server.store.migrate import current_revision, head_revision


def test_migrate_creates_and_upgrades_a_new_database(
    database_url: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["migrate", "--database-url", database_url]) == 0
    assert "empty ->" in capsys.readouterr().out
    engine = make_engine(database_url)
    try:
        head = head_revision(engine)
        assert current_revision(engine) == head
    finally:
        engine.dispose()
    assert main(["migrate", "--database-url", database_url]) == 0  # again: nothing to do
    assert f"{head} -> {head}" in capsys.readouterr().out


def test_migrate_defaults_to_sqlite_in_the_data_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from server.settings import get_settings

    monkeypatch.setenv("CROWDSLAM_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.delenv("CROWDSLAM_DATABASE_URL", raising=False)
    get_settings.cache_clear()
    try:
        assert main(["migrate"]) == 0
    finally:
        get_settings.cache_clear()
    assert (tmp_path / "data" / "crowdslam.sqlite3").exists()
    assert "sqlite:///" in capsys.readouterr().out


def test_unknown_command_fails(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["teleport"])
    assert exited.value.code == 2
    assert "invalid choice" in capsys.readouterr().err
