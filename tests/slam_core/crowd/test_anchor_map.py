from __future__ import annotations

import numpy as np
import pytest

from slam_core.crowd.anchor_map import CrowdMapBuilder
from slam_core.filter.params import BuildingAnchorParams

POSTERIOR = BuildingAnchorParams().type_posterior


def test_contributions_of_different_users_fuse_by_information() -> None:
    crowd = CrowdMapBuilder(POSTERIOR, detection_sigma_m=1e-3)
    a = crowd.contribute(0, np.array([10.0, 0.0]), np.eye(2) * 1.0, 0, 1.0)
    b = crowd.contribute(1, np.array([11.0, 0.0]), np.eye(2) * 3.0, 0, 2.0)
    assert a == b
    snap = crowd.snapshot()
    assert snap.mean[0, 0] == pytest.approx((10.0 / 1 + 11.0 / 3) / (1 / 1 + 1 / 3), abs=1e-3)
    assert snap.cov[0, 0] == pytest.approx(1 / (1 / 1 + 1 / 3), abs=1e-3)


def test_one_user_counts_once() -> None:
    crowd = CrowdMapBuilder(POSTERIOR, detection_sigma_m=1e-3)
    for _ in range(5):
        crowd.contribute(7, np.array([5.0, 5.0]), np.eye(2), 1, 0.0)
    assert crowd.snapshot().cov[0, 0] == pytest.approx(1.0, abs=1e-3)
    assert crowd.observation_counts()[0] == 5


def test_far_or_other_type_detections_start_new_anchors_and_known_ones_never_move() -> None:
    crowd = CrowdMapBuilder(POSTERIOR, detection_sigma_m=1.0)
    k = crowd.add_known(np.array([0.0, 0.0]), 0)
    assert crowd.contribute(0, np.array([0.5, 0.0]), np.eye(2) * 0.5, 0, 0.0) == k
    np.testing.assert_allclose(crowd.snapshot().mean[k], [0.0, 0.0])
    assert crowd.contribute(0, np.array([30.0, 0.0]), np.eye(2) * 0.5, 0, 0.0) != k
    assert len(crowd) == 2
    with pytest.raises(ValueError, match="finite"):
        crowd.contribute(0, np.array([np.nan, 0.0]), np.eye(2), 0, 0.0)


def test_signature_anchors_associate_by_identity_and_stay_out_of_particle_maps() -> None:
    crowd = CrowdMapBuilder(POSTERIOR, detection_sigma_m=0.5)
    plain = crowd.contribute(0, np.array([0.0, 0.0]), np.eye(2), 0, 1.0)
    a = crowd.contribute_signed(0, np.array([1.0, 0.0]), np.eye(2), 2, "beacon:aa", 2.0, 4.0)
    b = crowd.contribute_signed(1, np.array([30.0, 0.0]), np.eye(2), 2, "beacon:aa", 3.0, 4.0)
    assert a == b != plain  # identity, not position
    assert crowd.find_signature("beacon:aa") == a
    assert crowd.signature(a) == "beacon:aa"
    mean, cov, *_ = crowd.anchor(a)
    assert mean[0] == pytest.approx(15.5)  # equal information: the midpoint
    assert cov[0, 0] == pytest.approx((1.0 + 16.0) / 2)
    # a plain detection next to the signature anchor never joins it
    assert crowd.contribute(2, np.array([15.5, 0.0]), np.eye(2), 2, 4.0) not in (a, plain)
    assert a not in crowd.snapshot().crowd_id.tolist()
    assert crowd.informed_by_others(a, 0)
    lone = crowd.contribute_signed(5, np.zeros(2), np.eye(2), 3, "wifi:bb", 1.0, 4.0)
    assert not crowd.informed_by_others(lone, 5)
    assert crowd.informed_by_others(lone, 6)
    with pytest.raises(ValueError, match="signature"):
        crowd.contribute_signed(0, np.zeros(2), np.eye(2), 2, "", 1.0, 4.0)


def test_signature_survives_merge_restore_and_remove() -> None:
    crowd = CrowdMapBuilder(POSTERIOR, detection_sigma_m=0.5)
    plain = crowd.contribute(0, np.array([0.0, 0.0]), np.eye(2), 2, 1.0)
    signed = crowd.contribute_signed(1, np.array([1.0, 0.0]), np.eye(2), 2, "beacon:aa", 2.0, 4.0)
    crowd.merge(plain, signed)
    assert crowd.find_signature("beacon:aa") == plain
    assert crowd.signature(plain) == "beacon:aa"
    crowd.remove(plain)
    assert crowd.find_signature("beacon:aa") is None
    restored = crowd.restore(np.zeros(2), np.eye(2), 2, False, 3, 5.0, signature="wifi:cc")
    assert crowd.find_signature("wifi:cc") == restored


def test_association_weighs_type_confusion_against_a_new_anchor_as_eq_15_16_do() -> None:
    """An elevator (type 0) learned at the origin with covariance I; detections of covariance I (S = 2I).
    Eq. 16's new anchor scores log(p0 p(door | door)) = log(1e-3 * 0.8) = -7.13. A door detection (type 2;
    p(elevator | door) = 0.04) 0.5 m away scores log N + log 0.04 = -2.59 - 3.22 = -5.81 and joins; 2.5 m
    away (inside the 99 % gate) -7.31 and starts a new anchor, where an elevator detection there scores
    -4.32 and joins. (Leaving out every anchor with p(f | f_hat) < 0.05 instead would start a duplicate each
    time.)"""
    crowd = CrowdMapBuilder(POSTERIOR, detection_sigma_m=1e-3)
    elevator = crowd.contribute(0, np.zeros(2), np.eye(2), 0, 0.0)
    assert crowd.contribute(1, np.array([0.5, 0.0]), np.eye(2), 2, 1.0) == elevator
    fresh = CrowdMapBuilder(POSTERIOR, detection_sigma_m=1e-3)
    elevator = fresh.contribute(0, np.zeros(2), np.eye(2), 0, 0.0)
    door = fresh.contribute(1, np.array([2.5, 0.0]), np.eye(2), 2, 1.0)
    assert door != elevator
    again = CrowdMapBuilder(POSTERIOR, detection_sigma_m=1e-3)
    elevator = again.contribute(0, np.zeros(2), np.eye(2), 0, 0.0)
    assert again.contribute(1, np.array([2.5, 0.0]), np.eye(2), 0, 1.0) == elevator
    # a larger p0 makes new anchors cheaper: the near door detection then starts one too
    eager = CrowdMapBuilder(POSTERIOR, detection_sigma_m=1e-3, new_anchor_likelihood=0.05)
    elevator = eager.contribute(0, np.zeros(2), np.eye(2), 0, 0.0)
    assert eager.contribute(1, np.array([0.5, 0.0]), np.eye(2), 2, 1.0) != elevator


@pytest.mark.parametrize("p0", [0.0, -1.0, float("nan"), float("inf")])
def test_new_anchor_likelihood_must_be_positive_and_finite(p0: float) -> None:
    with pytest.raises(ValueError, match="new_anchor_likelihood"):
        CrowdMapBuilder(POSTERIOR, detection_sigma_m=0.5, new_anchor_likelihood=p0)
