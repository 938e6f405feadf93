"""Schemathesis against a live server, as an integrator would run it: ``st run URL/openapi.json --checks all``
with every phase (examples, coverage, fuzzing, stateful sequences along the spec's links), once with an
operator key and once with a device key, under the project's ``schemathesis.toml``. Any failure of any
check fails the test: a status, a content type, a header or a body the spec does not declare, a valid
request refused or an invalid one accepted, a 5xx."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.conftest import ROOT
from tests.server.api.conftest import Served

ST = Path(sys.executable).parent / "st"
EXAMPLES = 12
"""Generated requests per operation and phase here; ``docs/operations.md``'s run takes the default (100)."""


def _st_run(served: Served, key: str, tmp_path: Path) -> tuple[int, str]:
    command = [
        str(ST),
        "--config-file",
        str(ROOT / "schemathesis.toml"),
        "run",
        f"{served.base}/openapi.json",
        "--checks",
        "all",
        "--max-examples",
        str(EXAMPLES),
        "--seed",
        "1",
        "--workers",
        "1",
        "-H",
        f"Authorization: Bearer {served.keys[key]}",
    ]
    # its cache of failures to replay lives in the working directory: a fresh one, so runs do not depend
    # on each other
    done = subprocess.run(
        command,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "NO_COLOR": "1"},
    )
    return done.returncode, done.stdout + done.stderr


@pytest.mark.parametrize("key", ["operator", "device"])
def test_st_run_with_every_check_finds_nothing(served: Served, key: str, tmp_path: Path) -> None:
    code, output = _st_run(served, key, tmp_path)
    generated = re.search(r"(\d+) generated", output)
    summary = output[output.find("SUMMARY") :] if "SUMMARY" in output else output[-3000:]
    assert code == 0, output[:6000] + "\n...\n" + summary
    assert generated is not None, output[-3000:]
    assert int(generated.group(1)) >= 600, summary  # every operation, every phase
    for phase in ("Examples", "Coverage", "Fuzzing", "Stateful"):
        assert f"✅ {phase}" in output, summary


def _declared_links(spec: dict[str, Any]) -> list[tuple[str, str, str, str, dict[str, Any]]]:
    """(source path, source method, status, link name, link) for every link the spec declares."""
    return [
        (path, method, status, name, declared)
        for path, item in spec["paths"].items()
        for method, operation in item.items()
        for status, response in operation.get("responses", {}).items()
        for name, declared in response.get("links", {}).items()
    ]


def _target(spec: dict[str, Any], operation_ref: str) -> tuple[str, str, dict[str, Any]]:
    pointer = operation_ref.removeprefix("#/paths/").split("/")
    path = "/".join(pointer[:-1]).replace("~1", "/").replace("~0", "~")
    return path, pointer[-1], spec["paths"][path][pointer[-1]]


def test_every_declared_link_names_an_operation_and_values_it_has(served: Served) -> None:
    spec = served.spec
    declared = _declared_links(spec)
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
    spec = served.spec
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
