"""Pedestrian dead reckoning front-end: orientation, steps, step length and heading (pure numerics)."""
