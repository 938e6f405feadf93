"""A crash changes nothing: the scenario (``tests.server.crash.scenario``: three floors without a floor 0,
fixes, a tag with its floor, a lift pinned on floor 3 read as a start, rises, operators pinning, moving,
merging and deleting anchors, a floor plan, zones drawn and deleted with the crowd's visits, a signal map
loaded, a user forgotten, a key revoked) run with SIGKILLs at seeded points equals the same scenario run
without (``tests.server.crash.harness``).

Twenty kill points in all: eight on SQLite and eight on PostgreSQL (each the building's process or the whole
server), four of the worker holding the building in a cluster. ``bench/crash_anywhere.py`` runs more."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.server.cluster.cluster import local_cluster
from tests.server.crash.harness import InCluster, Run, differences, embedded, kill_points, play
from tests.server.crash.scenario import CrashScenario, crash_scenario

SEED = 58
"""Of the kill points: which steps, which target, how far into the step."""


@pytest.fixture(scope="module")
def scenario() -> CrashScenario:
    return crash_scenario()


@pytest.fixture(scope="module")
def reference(scenario: CrashScenario, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    """The scenario without a crash, once for the module (on SQLite: the store does not change the
    outcome)."""
    root = tmp_path_factory.mktemp("reference")
    with embedded(root) as server:
        yield play(scenario, server, [])
    shutil.rmtree(root, ignore_errors=True)


def _assert_same(reference: Run, crashed: Run, kills: int) -> None:
    assert len(crashed.kills) == kills
    assert crashed.duplicates_checked >= len(reference.acknowledged)
    found = differences(reference, crashed)
    assert found == [], "\n".join(found)


@pytest.mark.parametrize("store", ["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def test_a_crash_anywhere_changes_nothing(
    store: str,
    scenario: CrashScenario,
    reference: Run,
    request: pytest.FixtureRequest,
    tmp_path: Path,
) -> None:
    url = None if store == "sqlite" else str(request.getfixturevalue("postgres_url"))
    visits = [v for zone in reference.final["visits"].values() for v in zone]
    assert len(visits) >= 3  # the crowd visits the zones, and leaves some: what the crashes must keep
    assert any(v["left_ms"] is not None for v in visits)
    kills = kill_points(scenario, 8, SEED + (store == "postgresql"), ("building", "server"))
    assert {k.target for k in kills} == {"building", "server"}
    with embedded(tmp_path, url) as server:
        crashed = play(scenario, server, kills)
    _assert_same(reference, crashed, len(kills))


@pytest.mark.postgres
def test_a_crash_of_the_worker_holding_the_building_changes_nothing(
    scenario: CrashScenario, reference: Run, tmp_path: Path
) -> None:
    kills = kill_points(scenario, 4, SEED, ("worker",))
    with local_cluster(tmp_path, fronts=1, workers=2) as cluster:
        crashed = play(scenario, InCluster(cluster), kills)
    _assert_same(reference, crashed, len(kills))


def test_the_scenario_holds_what_the_crash_test_needs(scenario: CrashScenario) -> None:
    """Floors 1-3 only; a lift on floor 3 read as a start; a tag with its floor; rises (a phone's own, and
    barometers'); every operator edit."""
    assert os.environ.get("CROWDSLAM_BUILDING_PROCESSES") == "false"  # the harness asks for processes itself
    floors = [f["level"] for f in scenario.setup[0].body["floors"]]
    assert floors == [1, 2, 3]
    marks = [m for s in scenario.steps if s.batch is not None for m in s.batch.landmarks]
    assert any(m.kind == "anchor" for m in marks)
    assert any(m.kind == "tag" and "z3" in (m.payload or "") for m in marks)
    assert any(
        d.rise_m is not None for s in scenario.steps if s.batch is not None for d in s.batch.anchor_detections
    )
    assert any(s.batch is not None and s.batch.pressure is not None for s in scenario.steps)
    names = {s.name for s in scenario.steps if s.batch is None}
    assert {
        "pin the kiosk",
        "move the kiosk",
        "upload floor 2's plan",
        "merge dup-a and dup-b",
        "delete the kiosk",
        "draw zone-late",
        "delete zone-3",
        "signal map",
        "forget phone 4",
        "revoke",
    } <= names
