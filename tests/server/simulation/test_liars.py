"""A liar in the simulated crowd: its batches carry the victim's scans, made-up sightings of the victim and
fixes far from the truth; the evaluation scores only the honest users."""

from __future__ import annotations

import json

import pytest

from schemas.sensors import PositionFix
from server.settings import Settings
from server.simulation.evaluation import evaluate_scenario
from server.simulation.liars import OFFSET_M, liar_devices, lying
from server.simulation.phones import advertised_id, device_id, simulated_batches
from server.slam.config import ReplayOptions, load_calibration, tracker_params
from slam_core.sim.simulation import Scenario, simulate
from tests.conftest import TESTBED


def _small() -> Scenario:
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = 6
    raw["users"]["walk_length_m"] = 60.0
    return Scenario.from_dict(raw)


def test_a_liars_batches_are_rewritten_and_the_others_untouched() -> None:
    sim = simulate(_small(), 0)
    liars = liar_devices(6, 1)
    assert liars == {device_id(5)}
    honest = list(simulated_batches(sim, "b"))
    lied = list(lying(simulated_batches(sim, "b"), liars))
    assert len(lied) == len(honest)
    victim_scans = {
        tuple(ap.bssid for ap in s.aps) for b in honest if b.device_id == device_id(0) for s in b.wifi_scans
    }
    for before, after in zip(honest, lied, strict=True):
        if before.device_id not in liars:
            assert after == before
            continue
        assert all(tuple(ap.bssid for ap in s.aps) in victim_scans for s in after.wifi_scans)
        assert [s.peer_advertised_id for s in after.bluetooth] == [advertised_id(0)] * len(after.bluetooth)
        for was, now in zip(before.landmarks, after.landmarks, strict=False):
            assert isinstance(was, PositionFix)
            assert isinstance(now, PositionFix)
            assert now.position.x_m == pytest.approx(was.position.x_m + OFFSET_M)
    with pytest.raises(ValueError, match="no honest user"):
        liar_devices(2, 2)


def test_only_honest_users_are_scored() -> None:
    scenario = _small()
    base = (tracker_params(Settings()), load_calibration(None))
    honest, _ = evaluate_scenario(scenario, ReplayOptions(seed=0), *base)
    lied, _ = evaluate_scenario(scenario, ReplayOptions(seed=0, liars=1), *base)
    assert lied["liars"] == 1
    assert 0 < lied["n_estimates"] < honest["n_estimates"]
    assert lied["median_m"] < 3.0
