"""Every kind of bad batch, as a phone developer would send it: which status, which field, which message."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from typing import Any

import pytest

from schemas.catalog import EXAMPLES
from schemas.sensors import MAX_BATCH_BYTES, MAX_IMU_SAMPLES, SensorBatch, Step
from server.errors import ProblemError
from server.ingestion.decoding import decode_batch

Mutation = Callable[[dict[str, Any]], None]


def _set(path: str, value: Any) -> Mutation:
    def mutate(batch: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        node: Any = batch
        for part in parents:
            node = node[int(part)] if part.isdigit() else node[part]
        node[int(last) if last.isdigit() else last] = value

    return mutate


def _drop(key: str) -> Mutation:
    return lambda batch: batch.pop(key)


def _many_steps(n: int) -> Mutation:
    def mutate(batch: dict[str, Any]) -> None:
        batch["steps"] = [{"t_ms": 1700000000000 + i, "length_m": 0.7, "azimuth_rad": 0.0} for i in range(n)]

    return mutate


def _long_imu(n: int) -> Mutation:
    def mutate(batch: dict[str, Any]) -> None:
        batch["accelerometer"] = {
            "t_ms": [1700000000000 + i for i in range(n)],
            "x": [0.0] * n,
            "y": [0.0] * n,
            "z": [9.8] * n,
        }

    return mutate


# (case id, mutation of the valid example, expected status, expected error location, message fragment)
CASES: list[tuple[str, Mutation, int, str, str]] = [
    ("missing device", _drop("device_id"), 422, "device_id", "Field required"),
    ("wrong type for seq", _set("seq", "forty-two"), 422, "seq", "valid integer"),
    ("negative seq", _set("seq", -1), 422, "seq", "greater than or equal to 0"),
    ("bad identifier", _set("device_id", "phone 1/../x"), 422, "device_id", "String should match pattern"),
    ("unknown field", _set("colour", "red"), 422, "colour", "Extra inputs are not permitted"),
    (
        "rssi above 0",
        _set("wifi_scans.0.aps.0.rssi_dbm", 5),
        422,
        "wifi_scans.0.aps.0.rssi_dbm",
        "less than or equal to 0",
    ),
    (
        "rssi below -120",
        _set("wifi_scans.0.aps.1.rssi_dbm", -130),
        422,
        "wifi_scans.0.aps.1.rssi_dbm",
        "greater than or equal to -120",
    ),
    (
        "bad bssid",
        _set("wifi_scans.0.aps.0.bssid", "zz:zz"),
        422,
        "wifi_scans.0.aps.0.bssid",
        "String should match pattern",
    ),
    (
        "duplicate bssid",
        _set("wifi_scans.0.aps.1.bssid", "0E:74:9C:A7:B2:E4"),
        422,
        "wifi_scans.0",
        "appears twice",
    ),
    ("empty scan", _set("wifi_scans.0.aps", []), 422, "wifi_scans.0.aps", "at least 1 item"),
    (
        "time in seconds",
        _set("steps.0.t_ms", 1700000000),
        422,
        "steps.0.t_ms",
        "greater than or equal to 946684800000",
    ),
    (
        "imu time not increasing",
        _set("accelerometer.t_ms", [1700000000000, 1700000000000, 1700000000040]),
        422,
        "accelerometer.t_ms",
        "strictly increasing",
    ),
    (
        "imu columns differ",
        _set("accelerometer.x", [0.1, 0.2]),
        422,
        "accelerometer",
        "column 'x' has 2 values but t_ms has 3",
    ),
    (
        "not a unit quaternion",
        _set("rotation_vector.z", [0.38, 2.0, 0.39]),
        422,
        "rotation_vector",
        "not a unit quaternion",
    ),
    (
        "step without direction",
        _set("steps.0", {"t_ms": 1700000000500, "length_m": 0.7}),
        422,
        "steps.0",
        "needs azimuth_rad, heading_change_rad or both",
    ),
    ("step length zero", _set("steps.0.length_m", 0.0), 422, "steps.0.length_m", "greater than 0"),
    (
        "unknown bluetooth kind",
        _set("bluetooth.0.kind", "car"),
        422,
        "bluetooth.0",
        "does not match any of the expected tags",
    ),
    (
        "latitude out of range",
        _set(
            "landmarks.0",
            {"kind": "gps", "t_ms": 1700000000700, "lat_deg": 95.0, "lon_deg": 0.0, "accuracy_m": 5.0},
        ),
        422,
        "landmarks.0.gps.lat_deg",
        "less than or equal to 90",
    ),
    ("rsrp out of range", _set("lte.0.rsrp_dbm", -20.0), 422, "lte.0.rsrp_dbm", "less than or equal to -44"),
    (
        "malformed tag position",
        _set("landmarks.0.payload", "#6e1ebc forty,-74.4"),
        422,
        "landmarks.0.tag",
        "must read '#<id> <lat>,<lon> [z<floor>]'",
    ),
    (
        "tag position off the globe",
        _set("landmarks.0.payload", "#6e1ebc 95.0,-74.4 z0"),
        422,
        "landmarks.0.tag",
        "outside the WGS-84 range",
    ),
    ("too many steps", _many_steps(301), 422, "steps", "at most 300 items"),
    (
        "too many imu samples",
        _long_imu(MAX_IMU_SAMPLES + 1),
        422,
        "accelerometer.t_ms",
        f"at most {MAX_IMU_SAMPLES} items",
    ),
    (
        "pressure that is no air pressure",
        _set("pressure", {"t_ms": [1700000000000, 1700000000100], "value": [1001.0, 50.0]}),
        422,
        "body",
        "pressure.value[1] = 50.0 hPa is not an air pressure",
    ),
    (
        "batch spans two minutes",
        _set("steps.0.t_ms", 1700000120000),
        422,
        "body",
        "at most 60000 ms per batch",
    ),
]


@pytest.fixture
def example() -> dict[str, Any]:
    return copy.deepcopy(EXAMPLES["batch"])


def test_example_batch_is_valid(example: dict[str, Any]) -> None:
    batch = decode_batch(json.dumps(example).encode(), MAX_BATCH_BYTES)
    assert batch.effective_user_id == "phone-1"  # a device posts as itself
    assert batch.time_span_ms() == (1796559880000, 1796559880900)


@pytest.mark.parametrize(("case", "mutate", "status", "loc", "fragment"), CASES, ids=[c[0] for c in CASES])
def test_bad_batch_is_rejected_with_a_clear_problem(
    example: dict[str, Any], case: str, mutate: Mutation, status: int, loc: str, fragment: str
) -> None:
    mutate(example)
    body = json.dumps(example).encode()
    with pytest.raises(ProblemError) as caught:
        decode_batch(body, MAX_BATCH_BYTES * 4)
    problem = caught.value.to_problem()
    assert problem.status == status
    locs = [e.loc for e in problem.errors]
    assert loc in locs, f"{case}: expected an error at {loc}, got {locs}"
    messages = " | ".join(e.msg for e in problem.errors)
    assert fragment in messages, f"{case}: {fragment!r} not in {messages!r}"
    assert fragment in (problem.detail or "") or len(problem.errors) > 5


@pytest.mark.parametrize(
    ("literal", "loc"),
    [
        ("NaN", "accelerometer.x.1"),
        ("Infinity", "steps.0.length_m"),
        ("-Infinity", "wifi_scans.0.aps.0.rssi_dbm"),
    ],
)
def test_non_finite_numbers_are_rejected(example: dict[str, Any], literal: str, loc: str) -> None:
    target = loc.split(".")
    _set(loc, "__NONFINITE__")(example)
    body = json.dumps(example).replace('"__NONFINITE__"', literal).encode()
    with pytest.raises(ProblemError) as caught:
        decode_batch(body, MAX_BATCH_BYTES)
    problem = caught.value.to_problem()
    assert problem.status == 422
    assert any(e.loc == ".".join(target) and "finite number" in e.msg for e in problem.errors), problem.errors


@pytest.mark.parametrize(
    ("body", "status", "fragment"),
    [
        (b"", 400, "empty"),
        (b"   ", 400, "empty"),
        (b'{"building_id": "hq", ', 400, "not valid JSON"),
        (b"\xff\xfe", 400, "not valid JSON"),
        (b"[1, 2, 3]", 422, "should be an object"),
    ],
)
def test_malformed_bodies(body: bytes, status: int, fragment: str) -> None:
    with pytest.raises(ProblemError) as caught:
        decode_batch(body, MAX_BATCH_BYTES)
    problem = caught.value.to_problem()
    assert problem.status == status
    assert fragment in (problem.detail or "") + " ".join(e.msg for e in problem.errors)


def test_oversized_body_is_refused_before_parsing() -> None:
    body = b"x" * (MAX_BATCH_BYTES + 1)  # not even JSON: the size check must come first
    with pytest.raises(ProblemError) as caught:
        decode_batch(body, MAX_BATCH_BYTES)
    problem = caught.value.to_problem()
    assert problem.status == 413
    assert str(MAX_BATCH_BYTES) in (problem.detail or "")


def test_batch_with_only_steps_is_normal() -> None:
    batch = SensorBatch(
        building_id="hq",
        device_id="iphone-7",
        batch_id="b1",
        seq=0,
        steps=[Step(t_ms=1700000000000, length_m=0.7, heading_change_rad=0.1)],
    )
    assert batch.wifi_scans == []
    assert batch.accelerometer is None
    assert batch.effective_user_id == "iphone-7"


def test_empty_batch_has_no_time_span() -> None:
    batch = SensorBatch(building_id="hq", device_id="d", batch_id="b", seq=0)
    assert batch.time_span_ms() is None


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        ("#6e1ebc 40.684492,-74.401406 z0", (40.684492, -74.401406, 0)),
        ("#a1 -33.5,151.25 z-2", (-33.5, 151.25, -2)),
        ("#a1 10,20", (10.0, 20.0, 0)),
        ("meeting room 4", None),
        (None, None),
    ],
)
def test_tag_encoded_positions_are_parsed(
    payload: str | None, expected: tuple[float, float, int] | None
) -> None:
    from schemas.sensors import TagReading

    tag = TagReading(t_ms=1700000000000, tag_id="t1", payload=payload)
    assert tag.encoded_position() == expected
