"""A client nobody here wrote: ``openapi-python-client`` (or ``openapi-typescript``) generates one from the
live server's spec, and the newcomer's path runs through it unmodified: create a building, mint a device
key, post the example batch, read the positions, revoke the key, and see the next post refused."""

from __future__ import annotations

import contextlib
import copy
import importlib
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import httpx
import pytest

from schemas.catalog import EXAMPLES
from tests.server.api.conftest import Served

GENERATOR = Path(sys.executable).parent / "openapi-python-client"


@pytest.fixture(scope="module")
def client_package(served: Served, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ModuleType]:
    root = tmp_path_factory.mktemp("generated")
    spec = root / "openapi.json"
    spec.write_text(httpx.get(f"{served.base}/openapi.json").text)
    env = {**os.environ, "PATH": f"{GENERATOR.parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    done = subprocess.run(
        [
            str(GENERATOR),
            "generate",
            "--path",
            str(spec),
            "--meta",
            "none",
            "--output-path",
            "crowdslam_client",
        ],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    output = done.stdout + done.stderr
    assert done.returncode == 0, output
    assert "Warning" not in output, output  # every operation and model was generated
    sys.path.insert(0, str(root))
    try:
        yield importlib.import_module("crowdslam_client")
    finally:
        sys.path.remove(str(root))
        for name in [m for m in sys.modules if m == "crowdslam_client" or m.startswith("crowdslam_client.")]:
            del sys.modules[name]


def _module(package: ModuleType, name: str) -> Any:
    return importlib.import_module(f"{package.__name__}.{name}")


def test_the_newcomers_path_through_a_generated_client(served: Served, client_package: ModuleType) -> None:
    api = lambda name: _module(client_package, f"api.{name}")  # noqa: E731
    models = _module(client_package, "models")
    client = _module(client_package, "client")
    clients = contextlib.ExitStack()  # each client's connections closed at the end
    with clients:
        _newcomers_path(served, api, models, client, clients)


def _newcomers_path(
    served: Served, api: Any, models: Any, client: Any, clients: contextlib.ExitStack
) -> None:
    operator = clients.enter_context(
        client.AuthenticatedClient(base_url=served.base, token=served.keys["operator"])
    )

    created = api("buildings.create_building").sync_detailed(
        client=operator, body=models.Building(id="generated", name="Generated")
    )
    assert created.status_code == 201, created.content
    assert created.parsed.id == "generated"

    minted = api("buildings.create_key").sync(
        "generated",
        client=operator,
        body=models.DeviceKeyIn(scope="device", device_id="phone-1"),
    )
    assert isinstance(minted, models.KeyCreated), minted
    assert minted.scope == models.KeyScope.DEVICE
    assert minted.device_id == "phone-1"

    raw = copy.deepcopy(EXAMPLES["batch"])
    raw["building_id"] = "generated"
    device = clients.enter_context(client.AuthenticatedClient(base_url=served.base, token=minted.key))
    receipt = api("batches.post_batch").sync(
        "generated", client=device, body=models.SensorBatch.from_dict(raw)
    )
    assert isinstance(receipt, models.BatchReceipt), receipt
    assert receipt.status == models.BatchReceiptStatus.APPLIED
    assert receipt.tracking  # the example batch carries a position fix

    positions = api("positions.list_positions").sync("generated", client=operator)
    assert isinstance(positions, list), positions
    assert [p.user_id for p in positions] == [raw["device_id"]]  # a device posts as itself
    assert positions[0].t_ms == receipt.estimate.t_ms

    keys = api("buildings.list_keys").sync("generated", client=operator)
    assert [k.prefix for k in keys] == [minted.prefix]
    assert keys[0].created_at.tzinfo is not None  # RFC 3339 with its offset, parsed as such

    revoked = api("buildings.revoke_key").sync_detailed("generated", minted.prefix, client=operator)
    assert revoked.status_code == 204

    raw["batch_id"], raw["seq"] = "phone-1-000043", raw["seq"] + 1
    refused = api("batches.post_batch").sync_detailed(
        "generated", client=device, body=models.SensorBatch.from_dict(raw)
    )
    assert refused.status_code == 401
    assert isinstance(refused.parsed, models.Problem), refused.content
    assert refused.parsed.status == 401
    assert json.loads(refused.content)["title"] == "Unauthorized"


def test_the_generated_models_are_named_and_typed_as_the_api_reads(client_package: ModuleType) -> None:
    """Each key body takes its scope as the same plain string (no enum for one and a string for another),
    and no model is named after a route's internals (``...Response...``)."""
    models = _module(client_package, "models")
    bodies = {
        "DeviceKeyIn": {"scope": "device", "device_id": "phone-1"},
        "DashboardKeyIn": {"scope": "dashboard"},
        "BuildingOperatorKeyIn": {"scope": "operator"},
    }
    for name, body in bodies.items():
        model = getattr(models, name).from_dict(body)
        assert type(model.scope) is str, (name, type(model.scope))
        assert model.to_dict()["scope"] == body["scope"]
    names = [n for n in dir(models) if n[:1].isupper()]
    assert "GeoJsonExport" in names
    assert [n for n in names if "Response" in n] == []


TYPESCRIPT_PACKAGES = ("openapi-typescript@7", "openapi-fetch@0.14", "typescript@5", "@types/node@20")
TYPESCRIPT_CLIENT = """
import { readFileSync } from "node:fs";
import createClient from "openapi-fetch";
import type { components, paths } from "./schema.js";

type SensorBatch = components["schemas"]["SensorBatch"];
const [base, operatorKey, batchFile] = process.argv.slice(2);
const example: SensorBatch = JSON.parse(readFileSync(batchFile, "utf8"));
const building_id = "typescript";

function expect(what: string, ok: boolean, got: unknown): void {
  if (!ok) throw new Error(`${what}: ${JSON.stringify(got)}`);
}

const operator = createClient<paths>({ baseUrl: base, headers: { Authorization: `Bearer ${operatorKey}` } });
const created = await operator.POST("/v1/buildings", { body: { id: building_id, name: "TypeScript" } });
expect("create_building", created.response.status === 201 && created.data?.id === building_id, created.error);

const minted = await operator.POST("/v1/buildings/{building_id}/keys", {
  params: { path: { building_id } },
  body: { scope: "device", device_id: "phone-1" },
});
expect("create_key", minted.data?.scope === "device", minted.error);
const deviceKey: string = minted.data!.key;

const device = createClient<paths>({ baseUrl: base, headers: { Authorization: `Bearer ${deviceKey}` } });
const batch: SensorBatch = { ...example, building_id };
const receipt = await device.POST("/v1/buildings/{building_id}/batches", {
  params: { path: { building_id } },
  body: batch,
});
expect("post_batch", receipt.data?.status === "applied" && receipt.data.tracking, receipt.error);

const positions = await operator.GET("/v1/buildings/{building_id}/positions", {
  params: { path: { building_id } },
});
const users = (positions.data ?? []).map((estimate) => estimate.user_id);
expect("list_positions", users.length === 1 && users[0] === example.device_id, positions.data);

const revoked = await operator.DELETE("/v1/buildings/{building_id}/keys/{prefix}", {
  params: { path: { building_id, prefix: minted.data!.prefix } },
});
expect("revoke_key", revoked.response.status === 204, revoked.error);

const refused = await device.POST("/v1/buildings/{building_id}/batches", {
  params: { path: { building_id } },
  body: { ...batch, batch_id: "phone-1-000043", seq: batch.seq + 1 },
});
const problem: components["schemas"]["Problem"] | undefined = refused.error;
expect("refused", refused.response.status === 401 && problem?.status === 401, refused.error);
console.log(JSON.stringify({ applied: receipt.data!.status, refused: problem!.title }));
"""


def test_the_newcomers_path_through_a_generated_typescript_client(served: Served, tmp_path: Path) -> None:
    """The same path from TypeScript, as a dashboard's developer would: types from ``openapi-typescript``,
    calls through ``openapi-fetch``, type-checked by ``tsc --strict`` and run by node."""
    npm, node = shutil.which("npm"), shutil.which("node")
    if npm is None or node is None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail("node and npm are required under CI=true")
        pytest.skip("needs node and npm")
    (tmp_path / "package.json").write_text(
        '{"name": "crowdslam-ts-client", "private": true, "type": "module"}'
    )
    (tmp_path / "tsconfig.json").write_text(
        json.dumps(
            {
                "compilerOptions": {
                    "strict": True,
                    "target": "es2022",
                    "module": "nodenext",
                    "moduleResolution": "nodenext",
                    "outDir": "out",
                    "skipLibCheck": True,
                },
                "files": ["client.ts"],
            }
        )
    )

    def run(*argv: str) -> str:
        done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f"{' '.join(argv)}:\n{done.stdout}\n{done.stderr}"
        return done.stdout

    run(npm, "install", "--no-audit", "--no-fund", "--silent", *TYPESCRIPT_PACKAGES)
    run(
        str(tmp_path / "node_modules/.bin/openapi-typescript"),
        f"{served.base}/openapi.json",
        "-o",
        "schema.d.ts",
    )
    (tmp_path / "client.ts").write_text(TYPESCRIPT_CLIENT)
    (tmp_path / "batch.json").write_text(json.dumps(EXAMPLES["batch"]))
    run(str(tmp_path / "node_modules/.bin/tsc"), "-p", ".")
    answer = json.loads(run(node, "out/client.js", served.base, served.keys["operator"], "batch.json"))
    assert answer == {"applied": "applied", "refused": "Unauthorized"}
