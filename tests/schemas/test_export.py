"""The exported JSON Schemas in schemas/jsonschema are what the models produce, and examples are valid."""

from __future__ import annotations

import json
import re
from datetime import datetime
from pathlib import Path

import pytest

from schemas.catalog import EXAMPLE_MODELS, EXAMPLES, PUBLIC_MODELS, json_schemas
from schemas.live import LIVE_MESSAGE_ADAPTER
from server.cli.main import main

EXPORTED = Path(__file__).resolve().parents[2] / "schemas" / "jsonschema"


def test_committed_schemas_are_current() -> None:
    fresh = json_schemas()
    on_disk = {p.stem: json.loads(p.read_text()) for p in EXPORTED.glob("*.json")}
    assert sorted(on_disk) == sorted(fresh), "run `crowdslam schema --out schemas/jsonschema`"
    for name, schema in fresh.items():
        assert on_disk[name] == schema, (
            f"{name}.json is stale: run `crowdslam schema --out schemas/jsonschema`"
        )


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_examples_validate(name: str) -> None:
    EXAMPLE_MODELS[name].model_validate(EXAMPLES[name])


def test_every_public_model_has_a_schema_with_an_id() -> None:
    schemas = json_schemas()
    assert set(schemas) == set(PUBLIC_MODELS)
    for name, schema in schemas.items():
        assert schema["$id"].endswith(f"/{name}.json")


def test_live_envelope_is_discriminated_by_type() -> None:
    message = LIVE_MESSAGE_ADAPTER.validate_python({"type": "heartbeat", "t_ms": 1700000000000})
    assert message.type == "heartbeat"
    schema = json_schemas()["LiveMessage"]
    assert schema["discriminator"]["propertyName"] == "type"
    with pytest.raises(ValueError, match="does not match any of the expected tags"):
        LIVE_MESSAGE_ADAPTER.validate_python({"type": "weather", "t_ms": 1700000000000})


def test_cli_writes_schemas(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema", "--out", str(tmp_path)]) == 0
    written = sorted(p.name for p in tmp_path.glob("*.json"))
    assert written == sorted(f"{name}.json" for name in PUBLIC_MODELS)
    assert json.loads((tmp_path / "SensorBatch.json").read_text()) == json_schemas()["SensorBatch"]
    assert str(tmp_path / "SensorBatch.json") in capsys.readouterr().out


def test_cli_prints_a_valid_example_batch(capsys: pytest.CaptureFixture[str]) -> None:
    """A batch as the README asks phones to send one: no ``user_id`` (a device posts as itself), timed at the
    README's example instant, in the days a reader sees it, not years before."""
    assert main(["schema", "--example", "batch"]) == 0
    out = capsys.readouterr().out
    batch = EXAMPLE_MODELS["batch"].model_validate_json(out)
    assert "user_id" not in json.loads(out)
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    instant = re.search(r"RFC 3339 UTC \(`([0-9T:-]+Z)`\)", readme)
    assert instant is not None, "the README names its example instant"
    first = datetime.fromisoformat(instant.group(1)).timestamp() * 1000
    span = batch.time_span_ms()
    assert span is not None
    assert first <= span[0] <= span[1] < first + 60_000
