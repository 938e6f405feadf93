"""Live fan-out of a building's positions, encounters and anchors to dashboards (and to Foxglove)."""
