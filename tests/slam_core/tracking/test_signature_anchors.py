"""Signature anchors through the tracker: placed by one user, they correct another user's position; the
detection's report delay is bridged by dead reckoning; inconsistent ones are gated; own ones are ignored."""

from __future__ import annotations

import math

import numpy as np

from slam_core.encounters.models import Calibration, RangeModel
from slam_core.filter.params import BuildingAnchorParams, FilterParams, extended_confusion
from slam_core.tracking.tracker import BuildingTracker, TrackerParams, UserBatch

T0 = 1_700_000_000_000
CAL = Calibration(
    RangeModel("wifi-log", (0.0, 2.0), 3.0), RangeModel("bt-quadratic", (-60.0, -10.0, 0.0), 4.0)
)
BEACON = 6


def _walk(
    user: str,
    start: tuple[float, float],
    sigma: float,
    n_steps: int,
    t0: int,
    detect_at: int | None = None,
    observed_at: int | None = None,
    signature: str = "beacon:aa",
) -> UserBatch:
    """A fix, then ``n_steps`` steps of 1 m east; optionally a signature detection at step ``detect_at``."""
    step_t = t0 + 500 * (1 + np.arange(n_steps))
    batch = UserBatch(
        user=user,
        fix_t=np.array([t0], dtype=np.int64),
        fix_xy=np.array([start]),
        fix_sigma=np.array([sigma]),
        fix_azimuth=np.array([math.pi / 2]),
        step_t=step_t.astype(np.int64),
        step_length=np.ones(n_steps),
        step_azimuth=np.full(n_steps, math.pi / 2),
        step_turn=np.full(n_steps, np.nan),
    )
    if detect_at is None:
        return batch
    t = int(step_t[detect_at]) + 1
    return UserBatch(
        **{
            **batch.__dict__,
            "detect_t": np.array([t], dtype=np.int64),
            "detect_type": np.array([BEACON], dtype=np.int64),
            "detect_signature": (signature,),
            "detect_observed_t": np.array([observed_at if observed_at is not None else t], dtype=np.int64),
        }
    )


def _tracker() -> BuildingTracker:
    anchors = BuildingAnchorParams(confusion=extended_confusion(10))  # the server's ten anchor types
    params = TrackerParams(filter=FilterParams(anchors=anchors), crowd_solver="fusion", signature_sigma_m=1.0)
    return BuildingTracker(params, CAL, seed=3)


def test_another_users_anchor_pulls_a_lost_user_back() -> None:
    tracker = _tracker()
    # A starts exactly at (0, 0) and passes the beacon after 5 steps: the anchor is near (5, 0)
    tracker.apply([_walk("a", (0.0, 0.0), 0.1, 8, T0, detect_at=4)])
    # B really passes the beacon at (5, 0) too, but its start fix is 4 m off in y with a broad sigma
    before = _tracker()
    before.apply([_walk("b", (0.0, 4.0), 3.0, 8, T0 + 60_000)])
    outcome = tracker.apply([_walk("b", (0.0, 4.0), 3.0, 8, T0 + 60_000, detect_at=4)])
    assert outcome.reports["b"].signatures_applied == 1
    corrected = tracker.estimate("b")
    uncorrected = before.estimate("b")
    assert corrected is not None
    assert uncorrected is not None
    assert abs(corrected.y) < abs(uncorrected.y) - 1.0


def test_report_delay_is_bridged_by_dead_reckoning() -> None:
    """Detected at step 2 but reported at step 6: the anchor is placed where the user was at step 2."""
    tracker = _tracker()
    steps_t = T0 + 500 * (1 + np.arange(8))
    tracker.apply([_walk("a", (0.0, 0.0), 0.1, 8, T0, detect_at=6, observed_at=int(steps_t[2]))])
    index = tracker.crowd.find_signature("beacon:aa")
    assert index is not None
    mean, *_ = tracker.crowd.anchor(index)
    assert abs(mean[0] - 3.0) < 0.5
    assert abs(mean[1]) < 0.5


def test_inconsistent_and_own_anchors_are_not_applied() -> None:
    tracker = _tracker()
    tracker.apply([_walk("a", (0.0, 0.0), 0.1, 8, T0, detect_at=4)])
    # B is confidently 60 m away: the gate refuses the anchor
    far = tracker.apply([_walk("b", (0.0, 60.0), 0.3, 8, T0 + 60_000, detect_at=4)])
    assert far.reports["b"].signatures_gated == 1
    assert far.reports["b"].signatures_applied == 0
    # A's second pass: the anchor only holds A's own contribution (plus B's), so it now counts
    alone = _tracker()
    alone.apply([_walk("a", (0.0, 0.0), 0.1, 8, T0, detect_at=4)])
    again = alone.apply([_walk("a", (0.0, 0.0), 0.1, 8, T0 + 10_000, detect_at=4)])
    assert again.reports["a"].signatures_applied == 0
    assert again.reports["a"].signatures_gated == 0
