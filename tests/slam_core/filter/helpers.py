"""Compare one user of the engine with the textbook reference."""

from __future__ import annotations

import numpy as np

from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.filter.reference import ReferenceUser, from_state


def assert_matches(engine: DynamicSlam, u: int, ref: ReferenceUser, atol: float = 1e-9) -> None:
    s = engine.state
    np.testing.assert_allclose(s.x[u], [p.x for p in ref.particles], atol=atol, rtol=0)
    np.testing.assert_allclose(s.y[u], [p.y for p in ref.particles], atol=atol, rtol=0)
    np.testing.assert_allclose(s.heading[u], [p.heading for p in ref.particles], atol=atol, rtol=0)
    np.testing.assert_allclose(s.logw[u], [p.logw for p in ref.particles], atol=1e-7, rtol=0)
    np.testing.assert_array_equal(s.map_n[u], [len(p.anchors) for p in ref.particles])
    for m, p in enumerate(ref.particles):
        for k, a in enumerate(p.anchors):
            np.testing.assert_allclose(s.map_mu[u, m, k], a.mu, atol=atol, rtol=0)
            np.testing.assert_allclose(
                s.map_cov[u, m, k], [a.cov[0, 0], a.cov[0, 1], a.cov[1, 1]], atol=atol, rtol=0
            )
            assert s.map_type[u, m, k] == a.type
            assert s.map_count[u, m, k] == a.count
    assert int(s.rng_ctr[u]) == ref.rng.counter, (
        "the kernel and the reference drew different amounts of randomness"
    )


def to_reference(engine: DynamicSlam, u: int) -> ReferenceUser:
    return from_state(engine.state, u)
