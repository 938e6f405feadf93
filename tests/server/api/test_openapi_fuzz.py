"""Schemathesis generates requests from the OpenAPI spec (bounded examples per operation, then sequences
that follow the spec's links from one response to the next request) and sends them to a running server with
valid keys for each scope: whatever it sends, the server never answers 5xx."""

from __future__ import annotations

import contextlib
import copy
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
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


@dataclass(frozen=True)
class Served:
    base: str
    keys: dict[str, str]
    spec: dict[str, Any]
    template: Path
    """The database as the server started on it: building hq, an operator key and phone-1's device key."""


@contextlib.contextmanager
def _server(database: Path) -> Iterator[tuple[str, dict[str, Any]]]:
    app = create_app(Settings(data_dir=database.parent, database_url=f"sqlite:///{database}", record=False))
    with running_server(app, "127.0.0.1", free_port()) as base:
        yield base, copy.deepcopy(app.openapi())  # schemathesis rewrites the dict given: not the app's own


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    template = tmp_path_factory.mktemp("fuzz-template") / "db.sqlite3"
    engine = make_engine(f"sqlite:///{template}")
    upgrade(engine)
    with make_session_factory(engine).begin() as session:
        session.add(BuildingRow(id="hq", name="HQ", rotation_rad=0.0))
        session.flush()
        keys = {
            "operator": mint_key(session, KeyScope.OPERATOR)[0],
            "device": mint_key(session, KeyScope.DEVICE, "hq", "phone-1")[0],
        }
    engine.dispose()
    database = tmp_path_factory.mktemp("fuzz") / "db.sqlite3"
    shutil.copy(template, database)
    with _server(database) as (base, spec):
        yield Served(base, keys, spec, template)


EXAMPLES = int(os.environ.get("CROWDSLAM_FUZZ_EXAMPLES", "12"))
"""Generated requests per operation: 12 in the suite; ``CROWDSLAM_FUZZ_EXAMPLES=60`` for a long run. Twice as
many stateful sequences are run (of up to ``STEPS`` requests each)."""
STEPS = 6


def _headers(operation: Any, keys: dict[str, str]) -> dict[str, str]:
    scope = "device" if operation.path.endswith("/batches") else "operator"
    return {"Authorization": f"Bearer {keys[scope]}"}


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


def test_no_request_from_the_spec_makes_the_server_fail(served: Served) -> None:
    base, keys, spec = served.base, served.keys, served.spec
    failures: list[str] = []
    sent = [0]
    operations = 0
    for result in schemathesis.openapi.from_dict(spec).get_all_operations():
        if isinstance(result, Err):
            raise AssertionError(f"the OpenAPI spec has an invalid operation: {result.err()}")
        operation = result.ok()
        operations += 1
        _fuzz(operation, base, _headers(operation, keys), failures, sent)
    assert operations >= 10
    assert sent[0] >= operations  # every operation was called
    print(f"schemathesis: {sent[0]} requests over {operations} operations, {len(failures)} 5xx")
    assert not failures, "\n".join(failures[:10])


def test_sequences_through_the_links_make_no_5xx(
    served: Served, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """Stateful: a building created, then its keys minted and revoked, anchors pinned, read and deleted,
    builds started and polled, with the values each response gives, along the spec's links (and those
    schemathesis infers). Each sequence runs on a server of its own, started on a copy of the same
    database: Hypothesis draws a sequence's next step from the answers so far, which must not depend on
    earlier sequences."""
    keys = served.keys
    failures: list[str] = []
    sent = [0]
    followed: dict[str, dict[str, int]] = {"declared": {}, "inferred": {}}
    machine = schemathesis.openapi.from_dict(served.spec).as_state_machine()

    class Sequences(machine):  # type: ignore[misc, valid-type]
        def setup(self) -> None:
            database = tmp_path_factory.mktemp("sequence") / "db.sqlite3"
            shutil.copy(served.template, database)
            self.server = contextlib.ExitStack()
            self.base, _ = self.server.enter_context(_server(database))

        def teardown(self) -> None:
            self.server.close()

        def step(self, input: Any) -> Any:
            if input.transition is not None and input.is_applied:
                name = input.transition.id.split("] ")[1].split(" -> ")[0]  # "A -> [201] Name -> B"
                kind = "inferred" if input.transition.is_inferred else "declared"
                followed[kind][name] = followed[kind].get(name, 0) + 1
            return super().step(input)

        def get_call_kwargs(self, case: Any) -> dict[str, Any]:
            return {"base_url": self.base, "headers": _headers(case.operation, keys), "timeout": 30}

        def validate_response(self, response: Any, case: Any, *args: Any, **kwargs: Any) -> None:
            sent[0] += 1
            if response.status_code >= 500:
                failures.append(
                    f"{case.method} {case.formatted_path}: {response.status_code} {response.text[:300]}"
                )

    Sequences.run(
        settings=settings(
            max_examples=EXAMPLES * 2,
            stateful_step_count=STEPS,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            database=None,
            derandomize=True,
        )
    )
    print(f"schemathesis stateful: {sent[0]} requests, links followed {followed}, {len(failures)} 5xx")
    # which links a draw follows depends on the answers (fresh ids and keys): the spec's own links are walked
    # deterministically below
    assert sum(followed["declared"].values()) + sum(followed["inferred"].values()) >= EXAMPLES, followed
    assert not failures, "\n".join(failures[:10])


def _declared_links(spec: dict[str, Any]) -> Iterator[tuple[str, str, str, str, dict[str, Any]]]:
    """(source path, source method, status, link name, link) for every link the spec declares."""
    for path, item in spec["paths"].items():
        for method, operation in item.items():
            for status, response in operation.get("responses", {}).items():
                for name, declared in response.get("links", {}).items():
                    yield path, method, status, name, declared


def _target(spec: dict[str, Any], operation_ref: str) -> tuple[str, str, dict[str, Any]]:
    pointer = operation_ref.removeprefix("#/paths/").split("/")
    path = "/".join(pointer[:-1]).replace("~1", "/").replace("~0", "~")
    return path, pointer[-1], spec["paths"][path][pointer[-1]]


def _spec(served: Served) -> dict[str, Any]:
    """The spec as the server serves it (schemathesis rewrites the dict it is given)."""
    spec: dict[str, Any] = httpx.get(f"{served.base}/openapi.json").json()
    return spec


def test_every_declared_link_names_an_operation_and_values_it_has(served: Served) -> None:
    spec = _spec(served)
    declared = list(_declared_links(spec))
    assert len(declared) >= 10
    for path, method, status, name, declared_link in declared:
        target_path, target_method, target = _target(spec, declared_link["operationRef"])
        accepted = {p["name"] for p in target.get("parameters", [])}
        source = spec["paths"][path][method]
        source_params = {p["name"] for p in source.get("parameters", [])}
        body = source["responses"][status].get("content", {}).get("application/json", {}).get("schema", {})
        if "$ref" in body:
            body = spec["components"]["schemas"][body["$ref"].split("/")[-1]]
        for parameter, expression in declared_link["parameters"].items():
            assert parameter in accepted, f"{name}: {target_method} {target_path} takes no {parameter!r}"
            if expression.startswith("$request.path."):
                assert expression.removeprefix("$request.path.") in source_params, (name, expression)
            elif expression.startswith("$request.body#/"):
                request = source["requestBody"]["content"]
                schema = next(iter(request.values()))["schema"]
                if "$ref" in schema:
                    schema = spec["components"]["schemas"][schema["$ref"].split("/")[-1]]
                assert expression.removeprefix("$request.body#/") in schema["properties"], (name, expression)
            else:
                assert expression.startswith("$response.body#/"), (name, expression)
                field = expression.removeprefix("$response.body#/")
                assert field in body.get("properties", {}), f"{name}: the response has no {field!r}"


def test_the_links_of_a_new_building_lead_to_answers(served: Served) -> None:
    """Follow every link of ``POST /v1/buildings``'s answer as a client would, values filled in from it."""
    operator = {"Authorization": f"Bearer {served.keys['operator']}"}
    created = httpx.post(
        f"{served.base}/v1/buildings", json={"id": "linked", "name": "Linked"}, headers=operator
    )
    assert created.status_code == 201, created.text
    spec = _spec(served)
    source = spec["paths"]["/v1/buildings"]["post"]["responses"]["201"]["links"]
    bodies = {
        ("/v1/buildings/{building_id}/keys", "post"): {"scope": "dashboard"},
        ("/v1/buildings/{building_id}/anchors/{anchor_id}", "put"): {
            "type": "door",
            "position": {"x_m": 1.0, "y_m": 2.0},
        },
    }
    for name, declared_link in source.items():
        path, method, _ = _target(spec, declared_link["operationRef"])
        values = {"anchor_id": "linked-door"}
        for parameter, expression in declared_link["parameters"].items():
            values[parameter] = created.json()[expression.removeprefix("$response.body#/")]
        response = httpx.request(
            method, served.base + path.format(**values), json=bodies.get((path, method)), headers=operator
        )
        # each link leads to an answer: a signal-map build finds no recordings (409), all else works
        expected = {409} if name == "StartSignalMap" else {200, 201, 202}
        assert response.status_code in expected, (name, response.status_code, response.text[:300])
