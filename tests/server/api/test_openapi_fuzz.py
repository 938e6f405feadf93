"""Schemathesis generates requests from the OpenAPI spec (bounded examples per operation) and sends them to
a running server with valid keys for each scope: whatever it sends, the server never answers 5xx."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.core.result import Err

from schemas.api import KeyScope
from server.app import create_app
from server.auth import mint_key
from server.cli.background_server import free_port, running_server
from server.settings import Settings
from server.store.db import make_engine, make_session_factory
from server.store.migrate import upgrade
from server.store.models import BuildingRow


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, str], object]]:
    data: Path = tmp_path_factory.mktemp("fuzz")
    url = f"sqlite:///{data / 'db.sqlite3'}"
    engine = make_engine(url)
    upgrade(engine)
    with make_session_factory(engine).begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
        session.flush()
        keys = {
            "operator": mint_key(session, KeyScope.OPERATOR)[0],
            "device": mint_key(session, KeyScope.DEVICE, "hq", "phone-1")[0],
        }
    engine.dispose()
    app = create_app(Settings(data_dir=data, database_url=url, record=False))
    with running_server(app, "127.0.0.1", free_port()) as base:
        yield base, keys, app.openapi()


EXAMPLES = int(os.environ.get("CROWDSLAM_FUZZ_EXAMPLES", "12"))
"""Generated requests per operation: 12 in the suite; ``CROWDSLAM_FUZZ_EXAMPLES=60`` for a long run."""


def _fuzz(operation: Any, base: str, headers: dict[str, str], failures: list[str], sent: list[int]) -> None:
    @given(case=operation.as_strategy())
    @settings(
        max_examples=EXAMPLES,
        deadline=None,
        suppress_health_check=list(HealthCheck),
        database=None,
        derandomize=True,
    )
    def check(case: Any) -> None:
        response = case.call(base_url=base, headers=headers, timeout=30)
        sent[0] += 1
        if response.status_code >= 500:
            failures.append(
                f"{case.method} {case.formatted_path}: {response.status_code} {response.text[:300]}"
            )

    check()


def test_no_request_from_the_spec_makes_the_server_fail(
    served: tuple[str, dict[str, str], dict[str, object]],
) -> None:
    base, keys, spec = served
    failures: list[str] = []
    sent = [0]
    operations = 0
    for result in schemathesis.openapi.from_dict(spec).get_all_operations():
        if isinstance(result, Err):
            raise AssertionError(f"the OpenAPI spec has an invalid operation: {result.err()}")
        operation = result.ok()
        operations += 1
        scope = "device" if operation.path.endswith("/batches") else "operator"
        _fuzz(operation, base, {"Authorization": f"Bearer {keys[scope]}"}, failures, sent)
    assert operations >= 10
    assert sent[0] >= operations  # every operation was called
    print(f"schemathesis: {sent[0]} requests over {operations} operations, {len(failures)} 5xx")
    assert not failures, "\n".join(failures[:10])
