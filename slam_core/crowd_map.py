"""The building's shared anchor map, learned by the crowd ("DynamicSLAM learns anchors locations through
crowd-sourcing, which converges to the true anchor location over time", Section 4.1.1).

Each detection contributes the detecting user's position estimate (cloud mean, cloud covariance plus the
detection's R). A contribution is associated with the crowd anchor that minimises the Mahalanobis distance
minus twice the log type posterior p(f | f_hat), inside a 99 % chi-square gate; otherwise it starts a new
anchor. An anchor's estimate is the information-weighted fusion of its contributors, each user counted once
(its latest contribution), because one user's repeated passes share that user's drift and are not
independent. Operator-known anchors never move.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam_core.fastslam import CrowdMap

GATE_CHI2_99 = 9.21


@dataclass
class _CrowdAnchor:
    mean: np.ndarray
    cov: np.ndarray  # 2x2
    type: int
    known: bool
    contributions: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    observations: int = 0
    last_seen: float = -math.inf


class CrowdMapBuilder:
    def __init__(
        self,
        type_posterior: np.ndarray,
        detection_sigma_m: float,
        min_type_probability: float = 0.05,
        fuse: bool = True,
    ):
        """``fuse=False``: contributions only associate (and create anchors); positions come from
        ``set_estimate`` (the joint solve of ``slam_core.crowd_graph``)."""
        self._fuse = fuse
        self._posterior = np.asarray(type_posterior, dtype=float)
        self._r = detection_sigma_m**2
        self._min_type = min_type_probability
        self._anchors: list[_CrowdAnchor] = []

    def __len__(self) -> int:
        return len(self._anchors)

    def add_known(self, mean: np.ndarray, anchor_type: int) -> int:
        self._anchors.append(
            _CrowdAnchor(np.asarray(mean, float).copy(), np.eye(2) * 1e-4, int(anchor_type), True)
        )
        return len(self._anchors) - 1

    def contribute(self, user: int, mean: np.ndarray, cov: np.ndarray, detected_type: int, t: float) -> int:
        """Fuse one detection; returns the crowd anchor's index."""
        mean = np.asarray(mean, dtype=float)
        cov = np.asarray(cov, dtype=float) + self._r * np.eye(2)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise ValueError("contribution must be finite")
        best, best_score = -1, math.inf
        for k, anchor in enumerate(self._anchors):
            type_p = self._posterior[anchor.type, detected_type]
            if type_p < self._min_type:
                continue
            d = mean - anchor.mean
            m2 = float(d @ np.linalg.solve(anchor.cov + cov, d))
            if m2 > GATE_CHI2_99:
                continue
            score = m2 - 2.0 * math.log(type_p)
            if score < best_score:
                best, best_score = k, score
        if best < 0:
            self._anchors.append(_CrowdAnchor(mean.copy(), cov.copy(), int(detected_type), False))
            best = len(self._anchors) - 1
        anchor = self._anchors[best]
        anchor.observations += 1
        anchor.last_seen = t
        if not anchor.known:
            anchor.contributions[user] = (mean, cov)
            if self._fuse:
                self._refuse(anchor)
        return best

    def set_estimate(self, index: int, mean: np.ndarray, cov: np.ndarray) -> None:
        anchor = self._anchors[index]
        if anchor.known:
            raise ValueError(f"anchor {index} is operator-known; its position does not change")
        anchor.mean = np.asarray(mean, dtype=float).copy()
        anchor.cov = np.asarray(cov, dtype=float).copy()

    def means(self) -> dict[int, np.ndarray]:
        return {k: a.mean.copy() for k, a in enumerate(self._anchors)}

    @staticmethod
    def _refuse(anchor: _CrowdAnchor) -> None:
        info = np.zeros((2, 2))
        vec = np.zeros(2)
        for mean, cov in anchor.contributions.values():
            inv = np.linalg.inv(cov)
            info += inv
            vec += inv @ mean
        anchor.cov = np.linalg.inv(info)
        anchor.cov = 0.5 * (anchor.cov + anchor.cov.T)
        anchor.mean = anchor.cov @ vec

    def snapshot(self) -> CrowdMap:
        n = len(self._anchors)
        if n == 0:
            return CrowdMap.empty()
        return CrowdMap(
            mean=np.array([a.mean for a in self._anchors]),
            cov=np.array([[a.cov[0, 0], a.cov[0, 1], a.cov[1, 1]] for a in self._anchors]),
            type=np.array([a.type for a in self._anchors], dtype=np.int64),
            known=np.array([a.known for a in self._anchors], dtype=bool),
            crowd_id=np.arange(n, dtype=np.int64),
        )

    def observation_counts(self) -> np.ndarray:
        return np.array([a.observations for a in self._anchors], dtype=np.int64)
