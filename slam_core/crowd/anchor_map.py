"""The building's shared anchor map, learned by the crowd ("DynamicSLAM learns anchors locations through
crowd-sourcing, which converges to the true anchor location over time", Section 4.1.1).

Each detection contributes the detecting user's position estimate (cloud mean, cloud covariance plus the
detection's R). A contribution is associated as each particle associates its own detections (Eq. 15-16): with
the crowd anchor n that maximises N(d_n; 0, S_n) p(f_n | f_hat), d_n its offset and S_n the anchor's
covariance plus the contribution's, unless a new anchor's p0 p(f_hat | f_hat) is larger; a 99 % chi-square
gate bounds the offsets considered. Weighing a type confusion against a new anchor this way, rather than
leaving out anchors of an unlikely type, keeps a confused detection from starting a duplicate of the anchor
it stands at (``slam_core.sim.map_quality`` scores duplicates; docs/experiments.md has the figures). An
anchor's estimate is the information-weighted fusion of its contributors, each user counted once (its latest
contribution), because one user's repeated passes share that user's drift and are not independent.
Operator-known anchors never move.

Beyond the paper: every anchor lies on one floor (``level``), and a contribution is associated only with the
anchors of its user's floor: a staircase's landing upstairs is a place of its own, one storey above the one
downstairs. *Signature anchors* (a fixed beacon or WiFi AP heard strongly,
``slam_core.sensing.detectors``) carry an identity, so a contribution joins the anchor with its signature
whatever its position, and these anchors stay out of the particles' maps (the tracker observes them as
position measurements instead).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam_core.filter.dynamic_slam import CrowdMap

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
    removed: bool = False
    signature: str = ""
    level: int = 0


def _contribution(mean: np.ndarray, cov: np.ndarray, extra_variance: float) -> tuple[np.ndarray, np.ndarray]:
    """A detecting user's estimate as a contribution: its covariance plus the detection's own variance."""
    mean = np.asarray(mean, dtype=float)
    cov = np.asarray(cov, dtype=float) + extra_variance * np.eye(2)
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
        raise ValueError("contribution must be finite")
    return mean, cov


class CrowdMapBuilder:
    def __init__(
        self,
        type_posterior: np.ndarray,
        detection_sigma_m: float,
        new_anchor_likelihood: float = 1e-3,
        fuse: bool = True,
    ):
        """``new_anchor_likelihood``: p0 of Eq. 16 (per m^2), as the particles' own maps use it
        (``BuildingAnchorParams``). ``fuse=False``: contributions only associate (and create anchors);
        positions come from ``set_estimate`` (the joint solve of ``slam_core.crowd.graph``)."""
        if not (new_anchor_likelihood > 0 and math.isfinite(new_anchor_likelihood)):
            raise ValueError("new_anchor_likelihood must be a finite number > 0")
        self._fuse = fuse
        self._posterior = np.asarray(type_posterior, dtype=float)
        self._r = detection_sigma_m**2
        self._log_p0 = math.log(new_anchor_likelihood)
        self._anchors: list[_CrowdAnchor] = []
        self._by_signature: dict[tuple[int, str], int] = {}  # (level, signature): one transmitter per floor

    def __len__(self) -> int:
        """Anchors ever created (removed ones keep their index so ids stay stable)."""
        return len(self._anchors)

    def add_known(self, mean: np.ndarray, anchor_type: int, level: int = 0) -> int:
        self._anchors.append(
            _CrowdAnchor(
                np.asarray(mean, float).copy(), np.eye(2) * 1e-4, int(anchor_type), True, level=level
            )
        )
        return len(self._anchors) - 1

    def restore(
        self,
        mean: np.ndarray,
        cov: np.ndarray,
        anchor_type: int,
        known: bool,
        observations: int,
        t: float,
        signature: str = "",
        level: int = 0,
    ) -> int:
        """Re-create a stored anchor (after a restart): its estimate stands until new detections arrive."""
        mean = np.asarray(mean, dtype=float)
        cov = np.asarray(cov, dtype=float)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))) or np.linalg.det(cov) <= 0:
            raise ValueError("a stored anchor needs a finite mean and a positive definite covariance")
        anchor = _CrowdAnchor(mean.copy(), np.eye(2) * 1e-4 if known else cov.copy(), int(anchor_type), known)
        anchor.observations = int(observations)
        anchor.last_seen = t
        anchor.signature = signature
        anchor.level = level
        self._anchors.append(anchor)
        if signature:
            self._by_signature[(level, signature)] = len(self._anchors) - 1
        return len(self._anchors) - 1

    def pin(self, index: int, mean: np.ndarray, anchor_type: int, level: int | None = None) -> None:
        """An operator fixes an anchor's exact position, and its floor when given (it becomes known and never
        moves again)."""
        anchor = self._live(index)
        if level is not None and level != anchor.level:
            if anchor.signature:
                self._by_signature.pop((anchor.level, anchor.signature), None)
                self._by_signature[(level, anchor.signature)] = index
            anchor.level = level
        anchor.mean = np.asarray(mean, dtype=float).copy()
        anchor.cov = np.eye(2) * 1e-4
        anchor.type = int(anchor_type)
        anchor.known = True
        anchor.contributions.clear()

    def remove(self, index: int) -> None:
        """Drop an anchor from association and from snapshots; its index is never reused."""
        anchor = self._live(index)
        anchor.removed = True
        self._by_signature.pop((anchor.level, anchor.signature), None)

    def merge(self, keep: int, drop: int) -> None:
        """The crowd learned one anchor twice: ``drop``'s contributions join ``keep``, ``drop`` goes."""
        if keep == drop:
            raise ValueError("cannot merge an anchor into itself")
        target, source = self._live(keep), self._live(drop)
        if target.level != source.level:
            raise ValueError(
                f"anchors {keep} and {drop} lie on different floors ({target.level}, {source.level})"
            )
        target.observations += source.observations
        target.last_seen = max(target.last_seen, source.last_seen)
        if not target.known:
            for user, contribution in source.contributions.items():
                target.contributions.setdefault(user, contribution)
            if self._fuse and target.contributions:
                self._refuse(target)
        source.removed = True
        if source.signature:
            self._by_signature.pop((source.level, source.signature), None)
            if not target.signature:
                target.signature = source.signature
                self._by_signature[(target.level, target.signature)] = keep

    def is_live(self, index: int) -> bool:
        return 0 <= index < len(self._anchors) and not self._anchors[index].removed

    def _live(self, index: int) -> _CrowdAnchor:
        if not self.is_live(index):
            raise KeyError(f"no anchor {index} in the crowd map")
        return self._anchors[index]

    def anchor(self, index: int) -> tuple[np.ndarray, np.ndarray, int, bool, int, float]:
        """(mean, 2x2 cov, type, known, observations, last seen) of a live anchor."""
        a = self._live(index)
        return a.mean.copy(), a.cov.copy(), a.type, a.known, a.observations, a.last_seen

    def level(self, index: int) -> int:
        """The floor a live anchor lies on."""
        return self._live(index).level

    def contribute(
        self, user: int, mean: np.ndarray, cov: np.ndarray, detected_type: int, t: float, level: int = 0
    ) -> int:
        """Fuse one detection on floor ``level``; returns the crowd anchor's index."""
        mean, cov = _contribution(mean, cov, self._r)
        # Eq. 16: a new anchor; Eq. 15: each existing one (log likelihoods, eta cancels)
        best, best_score = -1, self._log_p0 + math.log(self._posterior[detected_type, detected_type])
        for k, anchor in enumerate(self._anchors):
            if anchor.removed or anchor.signature or anchor.level != level:
                continue
            type_p = self._posterior[anchor.type, detected_type]
            if type_p <= 0.0:
                continue
            d = mean - anchor.mean
            s = anchor.cov + cov
            m2 = float(d @ np.linalg.solve(s, d))
            if m2 > GATE_CHI2_99:
                continue
            score = -0.5 * m2 - 0.5 * math.log(float(np.linalg.det(2.0 * math.pi * s))) + math.log(type_p)
            if score > best_score:
                best, best_score = k, score
        if best < 0:
            best = self._new_anchor(mean, cov, detected_type, level)
        self._record(best, user, mean, cov, t)
        return best

    def find_signature(self, signature: str, level: int = 0) -> int | None:
        return self._by_signature.get((level, signature))

    def signature(self, index: int) -> str:
        return self._live(index).signature

    def informed_by_others(self, index: int, user: int) -> bool:
        """Known, or learned from at least one other user (a user's own past passes share its drift)."""
        anchor = self._live(index)
        return anchor.known or any(u != user for u in anchor.contributions)

    def contribute_signed(
        self,
        user: int,
        mean: np.ndarray,
        cov: np.ndarray,
        detected_type: int,
        signature: str,
        t: float,
        range_sigma_m: float,
        level: int = 0,
    ) -> int:
        """Fuse one detection of an identified transmitter on floor ``level`` (``range_sigma_m``: how far from
        it a strong reading may be); returns its anchor's index, creating it on first sight. A transmitter
        heard strongly on two floors is an anchor on each: where it peaks on the floor above is not where it
        hangs."""
        if not signature:
            raise ValueError("a signed contribution needs a signature")
        mean, cov = _contribution(mean, cov, range_sigma_m**2)
        index = self._by_signature.get((level, signature))
        if index is None:
            index = self._new_anchor(mean, cov, detected_type, level)
            self._anchors[index].signature = signature
            self._by_signature[(level, signature)] = index
        self._record(index, user, mean, cov, t)
        return index

    def _new_anchor(self, mean: np.ndarray, cov: np.ndarray, anchor_type: int, level: int = 0) -> int:
        self._anchors.append(_CrowdAnchor(mean.copy(), cov.copy(), int(anchor_type), False, level=level))
        return len(self._anchors) - 1

    def _record(self, index: int, user: int, mean: np.ndarray, cov: np.ndarray, t: float) -> None:
        """Count the detection; an unknown anchor keeps the user's latest contribution and is re-fused."""
        anchor = self._anchors[index]
        anchor.observations += 1
        anchor.last_seen = t
        if not anchor.known:
            anchor.contributions[user] = (mean, cov)
            if self._fuse:
                self._refuse(anchor)

    def set_estimate(self, index: int, mean: np.ndarray, cov: np.ndarray) -> None:
        anchor = self._anchors[index]
        if anchor.removed:
            return
        if anchor.known:
            raise ValueError(f"anchor {index} is operator-known; its position does not change")
        anchor.mean = np.asarray(mean, dtype=float).copy()
        anchor.cov = np.asarray(cov, dtype=float).copy()

    def means(self) -> dict[int, np.ndarray]:
        return {k: a.mean.copy() for k, a in enumerate(self._anchors) if not a.removed}

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

    def snapshot(self, level: int = 0) -> CrowdMap:
        """The anchors of floor ``level`` that the particles' own maps of its users may hold (signature
        anchors are observed by identity)."""
        live = [
            k for k, a in enumerate(self._anchors) if not a.removed and not a.signature and a.level == level
        ]
        if not live:
            return CrowdMap.empty()
        anchors = [self._anchors[k] for k in live]
        return CrowdMap(
            mean=np.array([a.mean for a in anchors]),
            cov=np.array([[a.cov[0, 0], a.cov[0, 1], a.cov[1, 1]] for a in anchors]),
            type=np.array([a.type for a in anchors], dtype=np.int64),
            known=np.array([a.known for a in anchors], dtype=bool),
            crowd_id=np.array(live, dtype=np.int64),
        )

    def observation_counts(self) -> np.ndarray:
        return np.array([a.observations for a in self._anchors], dtype=np.int64)
