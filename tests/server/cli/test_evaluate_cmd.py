"""``crowdslam evaluate`` on a small scenario: a single run, a comparison and a sweep write JSON and PNG."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from server.cli.main import main
from tests.conftest import TESTBED


@pytest.fixture
def small_scenario(tmp_path: Path) -> Path:
    raw = json.loads(TESTBED.read_text())
    raw["users"]["count"] = 4
    raw["users"]["walk_length_m"] = 40.0
    path = tmp_path / "small.json"
    path.write_text(json.dumps(raw))
    return path


def test_single_run_writes_metrics_and_a_cdf(
    small_scenario: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out" / "dyn.json"
    assert (
        main(["evaluate", "--scenario", str(small_scenario), "--mode", "dynamicslam", "--json", str(out)])
        == 0
    )
    result = json.loads(out.read_text())
    # the run ends with one line that says how it went, as the JSON does
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == (
        f"paper-testbed seed 0, dynamicslam: median {result['median_m']:.2f} m, p90 {result['p90_m']:.2f} m, "
        f"{result['n_estimates']:,} scored"
    )
    expected = {"mode", "median_m", "p75_m", "p90_m", "mean_m", "max_m", "n_estimates", "seconds"}
    expected |= {"anchors_passed_per_user", "encounters_per_user"}
    assert expected <= set(result)
    assert out.with_suffix(".png").stat().st_size > 1000


def test_compare_and_sweep(small_scenario: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "all.json"
    assert main(["evaluate", "--scenario", str(small_scenario), "--compare", "--json", str(out)]) == 0
    assert set(json.loads(out.read_text())) == {"pdr", "semanticslam", "dynamicslam"}
    from slam_core.sim import sweeps

    monkeypatch.setattr(sweeps, "sweep_values", lambda kind: [5, 20])
    sweep = tmp_path / "sweep.json"
    assert (
        main(["evaluate", "--scenario", str(small_scenario), "--sweep", "particles", "--json", str(sweep)])
        == 0
    )
    rows = json.loads(sweep.read_text())["rows"]
    assert [(r["value"], r["mode"]) for r in rows] == [
        (5, "semanticslam"), (5, "dynamicslam"), (20, "semanticslam"), (20, "dynamicslam")
    ]  # fmt: skip
    assert sweep.with_suffix(".png").exists()


def test_unreadable_scenario_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    assert main(["evaluate", "--scenario", str(bad), "--json", str(tmp_path / "x.json")]) == 2
    assert "cannot use scenario" in capsys.readouterr().out


def test_a_scenario_that_cannot_be_calibrated_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without WiFi no Eq. 3 range model can be fitted: ``calibrate`` says so. ``evaluate`` runs the world
    with the server's shipped models, as a server in such a building would (no scan, no WiFi encounter)."""
    raw = json.loads(TESTBED.read_text())
    raw["wifi"]["access_points"] = 0  # no WiFi pair to fit the Eq. 3 range model on
    raw["users"]["count"] = 4
    raw["users"]["walk_length_m"] = 20.0
    path = tmp_path / "no-wifi.json"
    path.write_text(json.dumps(raw))
    out = tmp_path / "x.json"
    assert main(["calibrate", "--scenario", str(path), "--out", str(out)]) == 2
    assert "labelled pairs to fit the wifi-log model" in capsys.readouterr().out
    assert not out.exists()
    assert main(["evaluate", "--scenario", str(path), "--mode", "dynamicslam", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["fingerprint_fixes_per_user"] == 0


def test_every_evaluation_runs_through_the_tracker(small_scenario: Path, tmp_path: Path) -> None:
    """A small crowd's phones (8 walking 40 m, so that some meet) one batch at a time through the server's
    tracker: one estimate per batch with steps, human anchors applied in dynamicslam and none in
    semanticslam, both better than plain dead reckoning; the same command gives the same figures, another
    filter seed other ones."""
    raw = json.loads(small_scenario.read_text())
    raw["users"]["count"] = 8
    crowd = tmp_path / "crowd.json"
    crowd.write_text(json.dumps(raw))
    results = {}
    for mode in ("pdr", "semanticslam", "dynamicslam"):
        out = tmp_path / f"{mode}.json"
        assert main(["evaluate", "--scenario", str(crowd), "--mode", mode, "--json", str(out)]) == 0
        results[mode] = json.loads(out.read_text())
        assert out.with_suffix(".png").stat().st_size > 1000
    # 8 users x 40 m at 1.4 m/s: ~29 one-second batches each, nearly all with steps
    assert 8 * 25 <= results["dynamicslam"]["n_estimates"] == results["pdr"]["n_estimates"] <= 8 * 35
    assert results["semanticslam"]["encounters_applied_per_user"] == 0
    assert results["dynamicslam"]["encounters_applied_per_user"] > 0
    for mode in ("semanticslam", "dynamicslam"):
        assert results[mode]["median_m"] < results["pdr"]["median_m"]

    def figures(*flags: str) -> tuple[float, float, int]:
        out = tmp_path / "again.json"
        assert main(["evaluate", "--scenario", str(crowd), *flags, "--json", str(out)]) == 0
        r = json.loads(out.read_text())
        return r["median_m"], r["p90_m"], r["n_estimates"]

    first = results["dynamicslam"]
    assert figures() == (first["median_m"], first["p90_m"], first["n_estimates"])
    other = figures("--filter-seed", "7")
    assert other[2] == first["n_estimates"]  # the same world and phones
    assert other[:2] != (first["median_m"], first["p90_m"])  # other filters' draws


@pytest.mark.parametrize("where", ["a folder", "a file in a file"])
def test_an_output_that_cannot_be_written_is_refused_before_the_run(
    small_scenario: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    """Checked when the command starts, not after a run of many minutes."""
    if where == "a folder":
        out = tmp_path
    else:
        (tmp_path / "plain").write_text("")
        out = tmp_path / "plain" / "out.json"
    with pytest.raises(SystemExit) as stopped:
        main(["evaluate", "--scenario", str(small_scenario), "--json", str(out)])
    assert stopped.value.code == 2
    assert "--json" in capsys.readouterr().err


def test_zones_are_scored_against_the_truth_and_the_point_test(small_scenario: Path, tmp_path: Path) -> None:
    out = tmp_path / "zones.json"
    assert main(["evaluate", "--scenario", str(small_scenario), "--zones", "--json", str(out)]) == 0
    zones = json.loads(out.read_text())["zones"]
    assert zones["zones"] == 30  # a room between the corridors, 6 x 5
    assert zones["true_visits"] >= 4
    for figures in (zones, zones["naive"]):
        assert {"visit_f1", "enter_delay_p50_s", "false_transitions_per_hour", "visits_matched"} <= set(
            figures
        )
    # four short walks: a few visits, so loose bounds (the testbed's figures are in docs/experiments.md)
    assert zones["visit_f1"] >= 0.6
    assert zones["false_transitions"] < zones["naive"]["false_transitions"]
    assert abs(zones["enter_delay_p50_s"]) <= 3.0
