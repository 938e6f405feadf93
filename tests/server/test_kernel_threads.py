"""``CROWDSLAM_KERNEL_THREADS``: a building's numba kernels run on that many threads (numba's setting is per
thread, so it is applied on the building's own thread); a value the machine cannot give fails the start."""

from __future__ import annotations

from pathlib import Path

import numba
import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.ingestion import BuildingWorker, set_kernel_threads
from server.settings import Settings
from tests.server.conftest import Api, migrate_with_operator
from tests.server.test_api import _batch

CORES = numba.config.NUMBA_NUM_THREADS


def test_more_kernel_threads_than_numba_has_are_refused() -> None:
    with pytest.raises(ValueError, match=f"kernel_threads is {CORES + 1}, but numba has {CORES} threads"):
        set_kernel_threads(CORES + 1)


def test_a_server_asked_for_more_kernel_threads_than_the_machine_has_does_not_start(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, kernel_threads=CORES + 1)
    with pytest.raises(ValueError, match="kernel_threads"), TestClient(create_app(settings)):
        pass


@pytest.mark.parametrize("threads", sorted({1, CORES}))
def test_a_buildings_kernels_run_on_the_configured_threads(tmp_path: Path, threads: int) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, kernel_threads=threads)
    with TestClient(create_app(settings)) as client:
        api = Api(client, operator, url, settings)
        api.create_building()
        device = api.key("hq", "device", "phone-1")
        assert (
            client.post("/v1/buildings/hq/batches", json=_batch(0), headers=api.auth(device)).status_code
            == 200
        )
        worker = client.app.state.crowdslam.tracking.workers["hq"]  # type: ignore[attr-defined]
        assert isinstance(worker, BuildingWorker)
        assert worker._executor.submit(numba.get_num_threads).result() == threads
