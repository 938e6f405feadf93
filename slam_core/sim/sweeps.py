"""The paper's sweeps (Figures 9, 11 and 13): one quantity of a scenario changed at a time."""

from __future__ import annotations

from slam_core.sim.simulation import Scenario

SWEEPS = ("particles", "density", "anchor-density")


def sweep_values(kind: str) -> list[float]:
    """The x axis of the paper's Figures 9 (particles), 11 (m^2 per user) and 13 (m^2 per anchor)."""
    if kind == "particles":
        return [1, 5, 10, 25, 50, 75, 100]
    if kind == "density":
        return [30, 60, 130, 300, 750, 1500]
    if kind == "anchor-density":
        return [100, 200, 400, 750, 1500]
    raise ValueError(f"unknown sweep {kind!r}; valid: {', '.join(SWEEPS)}")


def swept_scenario(scenario: Scenario, kind: str, value: float) -> Scenario:
    """The scenario with one quantity changed, as the paper's sweeps do (the rest stays as given)."""
    area = scenario["floor"]["width_m"] * scenario["floor"]["height_m"]
    if kind == "density":
        return scenario.with_setting("users", "count", max(2, round(area / value)))
    if kind == "anchor-density":
        count = max(scenario["building_anchors"]["known_positions"], round(area / value))
        return scenario.with_setting("building_anchors", "count", count)
    return scenario
