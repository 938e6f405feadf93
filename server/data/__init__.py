"""Files shipped with the server: the simulated testbed and its encounter calibration, and the manifest of
the public walks (``crowdslam datasets fetch``)."""

from __future__ import annotations

import argparse
from importlib import resources
from pathlib import Path

SCENARIOS = ("paper-testbed", "three-floors")
"""Scenarios the package ships, by name: ``--scenario paper-testbed`` (or ``three-floors``) on a clone with
nothing beside it."""


def shipped_scenario(name: str) -> Path:
    return Path(str(resources.files(__name__).joinpath(f"{name}.json")))


def scenario_argument(text: str) -> Path:
    """``--scenario``: a shipped scenario's name, or a scenario JSON file."""
    if text in SCENARIOS:
        return shipped_scenario(text)
    path = Path(text)
    if not path.is_file():
        raise argparse.ArgumentTypeError(
            f"{text}: no such file, nor a shipped scenario ({', '.join(SCENARIOS)})"
        )
    return path
