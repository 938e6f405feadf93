"""Move one user between the engine's arrays and the textbook reference's objects."""

from __future__ import annotations

import numpy as np

from slam_core.fastslam import DynamicSlam
from slam_core.reference import Anchor, CounterRng, Particle, ReferenceUser


def to_reference(engine: DynamicSlam, u: int) -> ReferenceUser:
    s = engine.state
    particles = []
    for m in range(s.n_particles):
        anchors = [
            Anchor(
                mu=s.map_mu[u, m, k].copy(),
                cov=np.array(
                    [
                        [s.map_cov[u, m, k, 0], s.map_cov[u, m, k, 1]],
                        [s.map_cov[u, m, k, 1], s.map_cov[u, m, k, 2]],
                    ]
                ),
                type=int(s.map_type[u, m, k]),
                count=int(s.map_count[u, m, k]),
                known=bool(s.map_known[u, m, k]),
                crowd_id=int(s.map_crowd_id[u, m, k]),
            )
            for k in range(s.map_n[u, m])
        ]
        particles.append(
            Particle(
                float(s.x[u, m]),
                float(s.y[u, m]),
                float(s.heading[u, m]),
                float(s.bias[u, m]),
                float(s.scale[u, m]),
                float(s.walk[u, m]),
                float(s.logw[u, m]),
                anchors,
            )
        )
    c = s.ctrl_cov[u]
    return ReferenceUser(
        particles=particles,
        rng=CounterRng(int(s.rng_key[u]), int(s.rng_ctr[u])),
        ctrl_cov=np.array([[c[0], c[1]], [c[1], c[2]]]),
        last_obs_heading=float(s.last_obs_heading[u]),
    )


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
