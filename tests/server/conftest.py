"""A migrated database, an app on it and keys for each scope."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from fastapi.testclient import TestClient

from schemas.api import KeyScope
from server.app import create_app
from server.auth import mint_key
from server.settings import Settings
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade


@dataclass
class Api:
    client: TestClient
    operator: str
    url: str
    settings: Settings

    def auth(self, key: str) -> dict[str, str]:
        return {"Authorization": f"Bearer {key}"}

    def create_building(
        self, building_id: str = "hq", geo: bool = False, size_m: tuple[float, float] | None = None
    ) -> None:
        body: dict[str, object] = {"id": building_id, "name": building_id.upper()}
        if size_m is not None:
            body["floors"] = [{"level": 0, "name": "Ground", "width_m": size_m[0], "height_m": size_m[1]}]
        if geo:
            body["geo_reference"] = {"origin_lat_deg": 47.6, "origin_lon_deg": -122.3, "rotation_rad": 0.3}
        response = self.client.post("/v1/buildings", json=body, headers=self.auth(self.operator))
        assert response.status_code == 201, response.text

    def key(self, building_id: str, scope: str, device_id: str | None = None) -> str:
        body: dict[str, object] = {"scope": scope}
        if device_id is not None:
            body["device_id"] = device_id
        response = self.client.post(
            f"/v1/buildings/{building_id}/keys", json=body, headers=self.auth(self.operator)
        )
        assert response.status_code == 201, response.text
        return str(response.json()["key"])


def migrate_with_operator(url: str) -> str:
    """Migrate the database at ``url`` to head and mint a site-wide operator key; returns the key."""
    engine = make_engine(url)
    upgrade(engine)
    with make_session_factory(engine).begin() as session:
        operator, _ = mint_key(session, KeyScope.OPERATOR)
    engine.dispose()
    return operator


def make_api(url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path_factory.mktemp("data"), database_url=url)
    with TestClient(create_app(settings)) as client:
        yield Api(client, operator, url, settings)


@pytest.fixture
def api(database_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    """The app on SQLite and on the local PostgreSQL."""
    yield from make_api(database_url, tmp_path_factory)


@pytest.fixture
def sqlite_api(sqlite_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    yield from make_api(sqlite_url, tmp_path_factory)
