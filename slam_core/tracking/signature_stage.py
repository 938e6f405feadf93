"""The tracker's signature stage (beyond the papers): a detection of an identified transmitter or signature
joins the crowd anchor of that identity and, once other users have placed that anchor, is a gated position
measurement of the user. Pure numerics.
"""

from __future__ import annotations

import math

import numpy as np

from slam_core.crowd.anchor_map import CrowdMapBuilder
from slam_core.crowd.graph import CrowdGraph
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.tracking.batches import UserReport
from slam_core.tracking.carry import carry_variance, trail_lookup
from slam_core.tracking.params import TrackerParams
from slam_core.tracking.rounds import Round
from slam_core.tracking.trails import Trails, UserTrack


class SignatureStage:
    """Over the building's crowd map and its graph, which the tracker shares with it."""

    def __init__(self, params: TrackerParams, crowd: CrowdMapBuilder, graph: CrowdGraph) -> None:
        self.sigma_m = params.signature_sigma_m
        self.gate_chi2 = params.signature_gate_chi2
        self.into_graph = params.crowd_solver == "graph"
        self.crowd = crowd
        self.graph = graph

    def observe(
        self,
        filters: DynamicSlam,
        users: dict[str, UserTrack],
        rnd: Round,
        signed: list[int],
        reports: dict[str, UserReport],
        trails: Trails,
    ) -> list[int]:
        """The round's signed detections ``signed`` (indices into its detections): the crowd anchor with that
        identity, once placed by other users, is a position measurement N(anchor; user, anchor cov +
        signature_sigma^2), gated at ``signature_gate_chi2`` against the user's cloud; then the user's
        pre-update estimate joins the anchor. The detection is reported after the closest approach it
        describes, so the user is placed at that moment through its own dead reckoning since (plus 10 % of
        the distance walked as variance). Each user appears at most once per round, so the tracker call is
        one batch. Returns the crowd anchors the detections joined."""
        crowd = self.crowd
        names = [rnd.det_users[k] for k in signed]
        slots = np.array([users[n].slot for n in names], dtype=np.int64)
        before = filters.summaries(slots)
        fix_slots, fix_xy, fix_sigma = [], [], []
        ids = []
        r2 = self.sigma_m**2
        observed = np.array([rnd.det_observed_t[k] for k in signed], dtype=np.int64)
        tracks = [users[n] for n in names]
        at_peak, walked_at_peak = trail_lookup(
            trails,
            slots,
            observed,
            np.array([u.last_t_ms for u in tracks], dtype=np.int64),
            np.array([u.displacement for u in tracks]),
            np.array([u.walked for u in tracks]),
        )
        for name, row, k, then, walked_then in zip(
            names, before, signed, at_peak, walked_at_peak, strict=True
        ):
            u = users[name]
            shift = u.displacement - then
            drift = float(carry_variance(u.walked - walked_then))
            cov = np.array([[row[2], row[3]], [row[3], row[4]]]) + drift * np.eye(2)
            level = int(filters.levels[u.slot])  # the transmitter's anchor on the user's floor
            existing = crowd.find_signature(rnd.det_signature[k], level)
            if existing is not None and crowd.informed_by_others(existing, u.number):
                anchor_mean, anchor_cov, *_ = crowd.anchor(existing)
                mean = anchor_mean + shift  # where the anchor says the user is now
                variance = float(np.max(np.linalg.eigvalsh(anchor_cov))) + r2 + drift
                d = mean - row[0:2]
                if float(d @ np.linalg.solve(cov + variance * np.eye(2), d)) <= self.gate_chi2:
                    fix_slots.append(u.slot)
                    u.pin()
                    fix_xy.append(mean)
                    fix_sigma.append(math.sqrt(variance))
                    reports[name].signatures_applied += 1
                else:
                    reports[name].signatures_gated += 1
            index = crowd.contribute_signed(
                u.number,
                row[0:2] - shift,
                cov,
                rnd.det_types[k],
                rnd.det_signature[k],
                float(rnd.det_observed_t[k]),
                self.sigma_m,
                level,
            )
            ids.append(index)
            if self.into_graph:
                self.graph.add_detection(u.number, index, then, walked_then, self.sigma_m)
        if fix_slots:
            filters.observe_position(
                np.array(fix_slots, dtype=np.int64), np.array(fix_xy), np.array(fix_sigma)
            )
        return ids
