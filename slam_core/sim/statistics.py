"""Error statistics (written here: evo is GPL-3.0)."""

from __future__ import annotations

import numpy as np


def error_summary(errors: np.ndarray) -> dict[str, float]:
    """Median, 75th and 90th percentiles, mean and max of position errors in metres."""
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        raise ValueError("no errors to summarise")
    if not np.all(np.isfinite(e)):
        raise ValueError("errors contain NaN or infinity")
    return {
        "median_m": float(np.median(e)),
        "p75_m": float(np.percentile(e, 75)),
        "p90_m": float(np.percentile(e, 90)),
        "mean_m": float(np.mean(e)),
        "max_m": float(np.max(e)),
    }


def empirical_cdf(errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted errors and their cumulative probabilities (i / n)."""
    e = np.sort(np.asarray(errors, dtype=float))
    return e, np.arange(1, e.size + 1) / e.size
