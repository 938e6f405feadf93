"""Accuracy on the simulated paper testbed (seed 0). Thresholds are what the engine reaches today, with a
margin; the issue's targets are tracked by ``crowdslam evaluate``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from slam_core.evaluation import run_scenario
from slam_core.simulate import Scenario

TESTBED = Path(__file__).resolve().parents[3] / "shared" / "scenarios" / "paper-testbed.json"


@pytest.fixture(scope="module")
def results() -> dict[str, dict[str, float]]:
    scenario = Scenario.from_dict(json.loads(TESTBED.read_text()))
    return {mode: run_scenario(scenario, 0, mode) for mode in ("pdr", "semanticslam", "dynamicslam")}


def test_building_anchors_beat_dead_reckoning(results: dict[str, dict[str, float]]) -> None:
    assert results["semanticslam"]["median_m"] < 0.6 * results["pdr"]["median_m"]
    assert results["semanticslam"]["p90_m"] < 0.7 * results["pdr"]["p90_m"]


def test_human_anchors_help(results: dict[str, dict[str, float]]) -> None:
    dyn, sem = results["dynamicslam"], results["semanticslam"]
    assert dyn["median_m"] <= 1.35
    assert dyn["median_m"] < sem["median_m"]
    assert dyn["p90_m"] < sem["p90_m"]
    assert 3 <= dyn["encounters_per_user"] <= 15  # the paper's testbed: about 7


def test_every_step_is_scored(results: dict[str, dict[str, float]]) -> None:
    for r in results.values():
        assert r["n_estimates"] > 23 * 340
        assert r["max_m"] < 30.0
