"""How well the crowd learned the building's anchor map, scored against a simulation's ground truth.

The testbed's gap between a learned and a perfect map is most of what is left of the error (seed 0: both
modes reach ~0.52 m on a perfect map), and DynamicSLAM's advantage over SemanticSLAM passes through the
map: users placed better by human anchors associate their detections with the right crowd anchors, so
the joint solve places the anchors better. These figures make that visible in every evaluation.

A crowd anchor stands for the true anchor most of its detections came from (its majority anchor).
"""

from __future__ import annotations

from collections import Counter

import numpy as np


def map_quality(
    detection_crowd_id: np.ndarray,
    detection_true_anchor: np.ndarray,
    crowd_means: dict[int, np.ndarray],
    known_crowd_ids: set[int],
    true_anchor_xy: np.ndarray,
) -> dict[str, float | None]:
    """Scores of a learned map: ``detection_crowd_id[i]`` is the crowd anchor detection i was associated
    with, ``detection_true_anchor[i]`` the true anchor it was of; ``crowd_means`` the map's final means
    (live anchors), ``known_crowd_ids`` the operator-known ones (exact, not scored for position).

    - ``map_anchors_learned``: crowd anchors learned from detections (known ones left out);
    - ``map_error_median_m`` / ``map_error_p90_m``: distance of each learned anchor's final mean to its
      majority anchor (None when none was learned: JSON's null, where NaN is not JSON);
    - ``map_duplicate_anchors``: crowd anchors beyond the first standing for the same true anchor (the crowd
      learned it twice);
    - ``map_misassociated_fraction``: detections whose crowd anchor stands for another true anchor.
    """
    ids = np.asarray(detection_crowd_id, dtype=np.int64)
    truth = np.asarray(detection_true_anchor, dtype=np.int64)
    if ids.shape != truth.shape or ids.ndim != 1:
        raise ValueError("detection_crowd_id and detection_true_anchor must be 1-D and equally long")
    if truth.size and (truth.min() < 0 or truth.max() >= len(true_anchor_xy)):
        raise ValueError("a detection's true anchor is not in true_anchor_xy")
    votes: dict[int, Counter[int]] = {}
    for c, a in zip(ids.tolist(), truth.tolist(), strict=True):
        votes.setdefault(c, Counter())[a] += 1
    majority = {c: v.most_common(1)[0][0] for c, v in votes.items()}
    wrong = sum(sum(v.values()) - v[majority[c]] for c, v in votes.items())
    stands_for = Counter(majority.values())
    errors = np.array(
        [
            float(np.linalg.norm(crowd_means[c] - true_anchor_xy[a]))
            for c, a in majority.items()
            if c in crowd_means and c not in known_crowd_ids
        ]
    )
    return {
        "map_anchors_learned": float(errors.size),
        "map_error_median_m": float(np.median(errors)) if errors.size else None,
        "map_error_p90_m": float(np.percentile(errors, 90)) if errors.size else None,
        "map_duplicate_anchors": float(sum(n - 1 for n in stands_for.values())),
        "map_misassociated_fraction": wrong / ids.size if ids.size else 0.0,
    }
