"""The engine's estimate rows and chosen encounters become wire ``Estimate``s and ``EncounterEvent``s (the
batch path's hottest conversions): equal to the models validated from their dumps, and a row that breaks the
schema's rules is refused naming it: as the client's (422) when it is a finite position out of range, with a
``ValueError`` (the server's) otherwise."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from schemas.estimates import EncounterEvent, Estimate, EstimateSource
from server.ingestion.convert import encounter_event, estimate
from slam_core.encounters.detection import (
    MODEL_BLUETOOTH,
    MODEL_WIFI,
    MODEL_WIFI_FINGERPRINT,
    RangedDetection,
)
from slam_core.geo import GeoFrame
from slam_core.tracking.tracker import EncounterResult, EstimateRow

GEO = GeoFrame(47.6, -122.3, 0.3)


def _row(rng: np.random.Generator) -> EstimateRow:
    a = rng.normal(0.0, 2.0, (2, 2))
    cov = a @ a.T + 1e-6 * np.eye(2)
    return EstimateRow(
        int(1_700_000_000_000 + rng.integers(0, 10**9)),
        float(rng.uniform(-500, 500)),
        float(rng.uniform(-500, 500)),
        (float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])),
        (float(rng.uniform(-500, 500)), float(rng.uniform(-500, 500))),
        float(rng.uniform(-20.0, 20.0)),  # the engine's heading is not wrapped
    )


@pytest.mark.parametrize("geo", [None, GEO])
def test_constructed_estimates_equal_validated_ones(geo: GeoFrame | None) -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        built = estimate(_row(rng), "hq", "user-1", "phone-1", geo, EstimateSource.DYNAMICSLAM)
        validated = Estimate.model_validate(built.model_dump())
        assert validated == built
        assert validated.model_dump_json() == built.model_dump_json()
        assert -math.pi <= built.heading_rad <= math.pi


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"x": math.nan}, "(?s)estimate of 'user-1' breaks the schema.*finite number"),
        ({"cov": (1.0, 0.0, math.inf)}, "finite number"),
        ({"cov": (1.0, 2.0, 1.0)}, "positive semi-definite"),
        ({"cov": (-1.0, 0.0, 1.0)}, "positive semi-definite"),
        ({"heading": math.nan}, "finite number"),
    ],
)
def test_an_estimate_breaking_the_schema_is_refused(change: dict[str, Any], message: str) -> None:
    row = replace(_row(np.random.default_rng(0)), **change)
    with pytest.raises(ValueError, match=message):
        estimate(row, "hq", "user-1", "phone-1", GEO if "x" in change else None, EstimateSource.DYNAMICSLAM)


def _encounter(rng: np.random.Generator, **change: Any) -> EncounterResult:
    fields: dict[str, Any] = {
        "t_ms": int(1_700_000_000_000 + rng.integers(0, 10**9)),
        "user_a": "user-1",
        "user_b": "user-2",
        "model": int(rng.choice([MODEL_WIFI, MODEL_WIFI_FINGERPRINT, MODEL_BLUETOOTH])),
        "feature": float(rng.uniform(-90.0, 10.0)),
        "distance_m": float(rng.exponential(5.0)),
        "variance_m2": float(rng.exponential(4.0)) + 1e-9,
    }
    return EncounterResult(RangedDetection(**(fields | change)), bool(rng.integers(0, 2)))


def test_constructed_encounters_equal_validated_ones() -> None:
    rng = np.random.default_rng(5)
    results = [_encounter(rng) for _ in range(200)]
    results += [_encounter(rng, distance_m=np.float64(350.0), variance_m2=np.float64(9e4))]  # clamped to 200
    models = set()
    for result in results:
        built = encounter_event(result, "hq")
        validated = EncounterEvent.model_validate(built.model_dump())
        assert validated == built
        assert validated.model_dump_json() == built.model_dump_json()
        models.add(built.model)
    assert len(models) == 3
    assert built.distance_m == built.distance_sigma_m == 200.0


@pytest.mark.parametrize(
    "change",
    [{"distance_m": math.nan}, {"distance_m": -0.5}, {"variance_m2": 0.0}, {"variance_m2": math.nan}],
)
def test_an_encounter_breaking_the_schema_is_refused(change: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="has no valid range"):
        encounter_event(_encounter(np.random.default_rng(0), **change), "hq")


def test_an_encounter_says_where_and_on_which_floor_the_two_met() -> None:
    base = _encounter(np.random.default_rng(1))
    met = encounter_event(replace(base, places=(1.0, 2.0, 3.5, -4.0), level=2), "hq")
    assert met.floor == 2
    assert met.position_a is not None
    assert met.position_b is not None
    assert (met.position_a.x_m, met.position_a.y_m, met.position_b.x_m, met.position_b.y_m) == (
        1.0,
        2.0,
        3.5,
        -4.0,
    )
    # an estimate carried off the map, or none: the event still goes, without places
    for places in ((1.0, math.nan, 0.0, 0.0), (1e9, 0.0, 0.0, 0.0), None):
        bare = encounter_event(replace(base, places=places), "hq")
        assert bare.position_a is None
        assert bare.position_b is None


@pytest.mark.parametrize(
    ("x", "geo", "clients"),
    [
        (100_002.0, None, True),  # finite, beyond where positions may be: the batch walked its user there
        (10.0, GeoFrame(89.99999, 0.0, 0.0), True),  # north of the pole: beyond WGS-84's range
        (math.nan, None, False),  # not finite: the engine's own failure
    ],
    ids=["beyond-the-local-range", "beyond-wgs84", "not-finite"],
)
def test_an_estimate_out_of_range_is_the_clients_and_a_broken_one_the_servers(
    x: float, geo: GeoFrame | None, clients: bool
) -> None:
    """A finite estimate beyond the positions the schema allows is refused as the batch's (422: its fixes
    and steps took the user there); anything else the schema refuses is the engine's failure (a 500)."""
    from server.errors import InvalidInputError

    row = replace(_row(np.random.default_rng(3)), x=x, y=2_000.0 if geo is not None else 5.0)
    with pytest.raises((ValueError, InvalidInputError), match="u-1") as refused:
        estimate(row, "hq", "u-1", "d-1", geo, EstimateSource.DYNAMICSLAM)
    assert isinstance(refused.value, InvalidInputError) == clients
