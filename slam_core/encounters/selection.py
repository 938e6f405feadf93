"""Which detected encounters become human anchors: chosen on the filters' prediction, not on the reading.

The paper detects an encounter when the reading passes its model's threshold (Eq. 3 below 8 dB; Bluetooth
above -90 dBm, Table 2) and applies it (Algorithm 1). Applying every detection double counts (a pair walking
together is detected every second), and choosing *which* detections to apply by their measured value (the
first reading that looks informative, then a cooldown) picks readings with lucky noise: on the simulated
testbed those encounters under-reported the distance by 1.6 m (median; mean 2.3 m), pulling users together,
and their per-bin R was inflated by far pairs that read strong by chance (the base rate of far pairs is
high).

Beyond the paper, the choice here depends only on the two filters' current estimates, so the chosen readings
keep the measurement's own, unbiased, noise:

1. the pair's predicted distance ``||mu_a - mu_b||`` is at most ``select_range_m``;
2. the model's range standard deviation *at that predicted distance* is at most ``max_sigma_m`` (an
   encounter that cannot say much is not worth the risk of double counting);
3. the pair (per model) has not had an encounter applied in the last ``pair_cooldown_ms``: successive
   updates against the same peer reuse the peer's error, so they are spaced out.

Within one call, a pair's latest reading is the one considered (its pair average is over both directions).
A wrong or far encounter that is chosen anyway is caught by the filter's Mahalanobis gate and outlier term.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np


@dataclass(frozen=True)
class SelectionParams:
    select_range_m: float = 8.0
    """Pairs the filters place within 8 m: about the Bluetooth range where a reading's range error stays
    below 2 m (Figure 2's fit on the testbed: 4 dB per reading, 22 dB per decade of distance)."""
    max_sigma_m: float = 5.0
    pair_cooldown_ms: int = 5_000

    def __post_init__(self) -> None:
        if self.select_range_m <= 0 or self.max_sigma_m <= 0:
            raise ValueError("select_range_m and max_sigma_m must be > 0")
        if self.pair_cooldown_ms < 0:
            raise ValueError("pair_cooldown_ms must be >= 0")


class EncounterSelector:
    """Per-pair cooldowns of one building (or one evaluation run)."""

    def __init__(self, params: SelectionParams) -> None:
        self.params = params
        self._last_applied: dict[Hashable, int] = {}
        self.n_considered = 0
        self.n_chosen = 0

    def choose(
        self,
        t_ms: np.ndarray,
        pair_keys: Sequence[Hashable] | np.ndarray,
        predicted_m: np.ndarray,
        sigma_at_prediction_m: np.ndarray,
    ) -> np.ndarray:
        """Boolean mask of the readings to apply. ``pair_keys[i]`` identifies reading i's unordered pair and
        model (``pair_key``, or an int64 array from ``pair_keys``); ``predicted_m`` is the filters' distance
        between the two users; ``sigma_at_prediction_m`` is the model's range standard deviation at that
        distance. The chosen pairs start their cooldown. Vectorised but for the cooldowns of the readings
        that pass both gates: a busy building has thousands of readings per call."""
        t_ms = np.asarray(t_ms, dtype=np.int64)
        predicted_m = np.asarray(predicted_m, dtype=np.float64)
        sigma_at_prediction_m = np.asarray(sigma_at_prediction_m, dtype=np.float64)
        n = t_ms.shape[0]
        if not (len(pair_keys) == predicted_m.shape[0] == sigma_at_prediction_m.shape[0] == n):
            raise ValueError("t_ms, pair_keys, predicted_m and sigma_at_prediction_m must be equally long")
        if not (np.all(np.isfinite(predicted_m)) and np.all(np.isfinite(sigma_at_prediction_m))):
            raise ValueError("predicted distances and sigmas must be finite")
        chosen = np.zeros(n, dtype=bool)
        if n == 0:
            return chosen
        p = self.params
        keys = pair_keys if isinstance(pair_keys, np.ndarray) else _codes(pair_keys)
        latest = latest_per_pair(t_ms, keys)
        self.n_considered += int(latest.size)
        gated = latest[
            (predicted_m[latest] <= p.select_range_m) & (sigma_at_prediction_m[latest] <= p.max_sigma_m)
        ]
        for i in gated.tolist():
            key = pair_keys[i] if not isinstance(pair_keys, np.ndarray) else int(pair_keys[i])
            last = self._last_applied.get(key)
            if last is not None and t_ms[i] - last < p.pair_cooldown_ms:
                continue
            self._last_applied[key] = int(t_ms[i])
            chosen[i] = True
            self.n_chosen += 1
        return chosen

    def __len__(self) -> int:
        """Pairs with a remembered cooldown."""
        return len(self._last_applied)

    def forget_before(self, t_ms: int) -> None:
        """Drop cooldowns that ended before ``t_ms`` (bounded memory in a long-running building)."""
        horizon = t_ms - self.params.pair_cooldown_ms
        self._last_applied = {k: v for k, v in self._last_applied.items() if v >= horizon}


def latest_per_pair(t_ms: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Indices, in increasing order, of each pair's latest reading (the last of equal times): the only
    reading of a pair ``EncounterSelector.choose`` considers, so a caller may narrow its input to them."""
    backwards = np.argsort(np.asarray(t_ms), kind="stable")[::-1]
    _, first = np.unique(np.asarray(keys)[backwards], return_index=True)
    latest: np.ndarray = np.sort(backwards[first])
    return latest


def _codes(keys: Sequence[Hashable]) -> np.ndarray:
    """Hashable keys as integer codes (equal keys, equal codes)."""
    index: dict[Hashable, int] = {}
    return np.array([index.setdefault(k, len(index)) for k in keys], dtype=np.int64)


UserId = TypeVar("UserId", int, str)

_ID_BITS = 29
"""Users ids below 2^29 in ``pair_keys``: two ids and the model's two bits fill 60 bits of an int64."""


def pair_key(a: UserId, b: UserId, model: int) -> tuple[UserId, UserId, int]:
    """The unordered pair and its model, as ``choose`` expects."""
    return (min(a, b), max(a, b), model)


def pair_keys(a: np.ndarray, b: np.ndarray, model: np.ndarray) -> np.ndarray:
    """``pair_key`` of integer user ids (in [0, 2^29)) and models (in [0, 4)) as one int64 per reading."""
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    model = np.asarray(model, dtype=np.int64)
    if a.size and (min(a.min(), b.min(), model.min()) < 0 or max(a.max(), b.max()) >= 1 << _ID_BITS):
        raise ValueError(f"pair keys need user ids in [0, 2^{_ID_BITS}) and models >= 0")
    if model.size and model.max() >= 4:
        raise ValueError("pair keys need models in [0, 4)")
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keys: np.ndarray = (((lo << _ID_BITS) | hi) << 2) | model
    return keys
