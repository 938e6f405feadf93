"""What the server says of its disk: the data directory's and the database's sizes and the free space, as
metrics and in /healthz, which is degraded below ``CROWDSLAM_MIN_FREE_DISK_GB``."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from server.app import create_app
from server.settings import Settings
from server.storage import StorageWatch, database_bytes, tree_bytes
from server.store.db import make_engine
from tests.server.conftest import migrate_with_operator


def test_the_sizes_are_what_the_files_hold_and_measured_again_a_minute_later(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'crowdslam.sqlite3'}"
    migrate_with_operator(url)
    engine = make_engine(url)
    (tmp_path / "recordings" / "hq").mkdir(parents=True)
    (tmp_path / "recordings" / "hq" / "20261206T12.mcap").write_bytes(b"x" * 1000)
    watch = StorageWatch(tmp_path, engine)
    first = watch.storage()
    database = database_bytes(engine)
    assert first.database_bytes == database > 0
    assert first.data_dir_bytes == tree_bytes(tmp_path) >= database + 1000
    assert first.free_bytes > 0
    (tmp_path / "recordings" / "hq" / "20261206T13.mcap").write_bytes(b"x" * 5000)
    assert watch.storage().data_dir_bytes == first.data_dir_bytes  # within the minute: as measured
    watch._sizes = (watch._sizes[0] - 61.0, *watch._sizes[1:])  # type: ignore[index]
    assert watch.storage().data_dir_bytes == first.data_dir_bytes + 5000
    engine.dispose()


def test_healthz_is_degraded_on_a_disk_short_of_space_and_metrics_give_the_sizes(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'crowdslam.sqlite3'}"
    migrate_with_operator(url)
    for threshold_gb, status in ((0.0, "ok"), (1e9, "degraded")):  # a disk of an exabyte free: none is
        settings = Settings(data_dir=tmp_path, database_url=url, min_free_disk_gb=threshold_gb)
        with TestClient(create_app(settings)) as client:
            health = client.get("/healthz").json()
            metrics = client.get("/metrics").text
        assert health["status"] == status
        assert health["low_disk"] is (status == "degraded")
        assert health["disk_free_bytes"] > 0
    for name in ("crowdslam_data_dir_bytes", "crowdslam_database_bytes", "crowdslam_disk_free_bytes"):
        line = next(line for line in metrics.splitlines() if line.startswith(name + " "))
        assert float(line.split()[1]) > 0, line
