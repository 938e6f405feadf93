"""A small floor made of six of the sample's walks (symlinked in place), for the replay and CLI tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.conftest import SAMPLE_FLOOR

FLOOR = SAMPLE_FLOOR
WALKS = (
    "5dd9fd499191710006b570de",
    "5dd9efa5c5b77e0006b17365",
    "5dd9efa29191710006b5708a",
    "5dda0216c5b77e0006b17408",
    "5ddb9632c5b77e0006b179b1",
    "5dd9e7c79191710006b57067",
)


@pytest.fixture(scope="module")
def small_floor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    floor = tmp_path_factory.mktemp("floor") / "F1"
    (floor / "path_data_files").mkdir(parents=True)
    shutil.copy(FLOOR / "floor_info.json", floor / "floor_info.json")
    for name in WALKS:
        (floor / "path_data_files" / f"{name}.txt").symlink_to(FLOOR / "path_data_files" / f"{name}.txt")
    return floor


@pytest.fixture(scope="module")
def small_building(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two floors, F1 and F2 (levels 0 and 1), of three of the sample's walks each: a building's folder as the
    data set lays one out."""
    building = tmp_path_factory.mktemp("building")
    for floor_name, names in (("F1", WALKS[:3]), ("F2", WALKS[3:])):
        floor = building / floor_name
        (floor / "path_data_files").mkdir(parents=True)
        shutil.copy(FLOOR / "floor_info.json", floor / "floor_info.json")
        for name in names:
            (floor / "path_data_files" / f"{name}.txt").symlink_to(FLOOR / "path_data_files" / f"{name}.txt")
    return building
