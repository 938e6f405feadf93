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
   updates against the same peer reuse the peer's error, so they are spaced out;
4. neither user has used up its allowance: ``user_rate_per_s`` encounters a second on average, up to
   ``user_burst`` at once (a token bucket), the most informative readings (smallest range sigma at the
   predicted distance) first. In a crowd a user within range of dozens of peers would take several a
   second, each pulling it towards peers whose errors it already shares once they have met, which counts
   the same information again; passing a group, a user still takes a few at once.

Within one call, a pair's latest reading is the one considered (its pair average is over both directions).
A wrong or far encounter that is chosen anyway is caught by the filter's Mahalanobis gate and outlier term.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np
from numba import njit

from slam_core.encounters.detection import DetectionArrays, EncounterDetector
from slam_core.encounters.sighting_pairs import home_slot
from slam_core.filter.dense_ids import unique_ints, unique_ints_inverse


@dataclass(frozen=True)
class SelectionParams:
    select_range_m: float = 8.0
    """Pairs the filters place within 8 m: about the Bluetooth range where a reading's range error stays
    below 2 m (Figure 2's fit on the testbed: 4 dB per reading, 22 dB per decade of distance)."""
    max_sigma_m: float = 5.0
    pair_cooldown_ms: int = 5_000
    user_rate_per_s: float = 1.0
    """Encounters a user takes a second on average (the simulated testbed's users take ~0.3 a second; in the
    load benchmark's dense crowd they were offered 2-4)."""
    user_burst: float = 3.0

    def __post_init__(self) -> None:
        if self.select_range_m <= 0 or self.max_sigma_m <= 0:
            raise ValueError("select_range_m and max_sigma_m must be > 0")
        if self.pair_cooldown_ms < 0:
            raise ValueError("pair_cooldown_ms must be >= 0")
        if not (self.user_rate_per_s > 0 and self.user_burst >= 1):
            raise ValueError("user_rate_per_s must be > 0 and user_burst >= 1")


class EncounterSelector:
    """Per-pair cooldowns and per-user allowances of one building (or one evaluation run), kept as arrays
    that one compiled call reads and updates for a whole tracker call's readings (``_choose``): a hash
    table of pair keys and the time each pair last had an encounter applied, and each user's tokens left
    and the time it last took one."""

    def __init__(self, params: SelectionParams) -> None:
        self.params = params
        self._pairs = _PairTable()
        self._left = np.zeros(0)  # by user id: the allowance left when it last took one
        self._since = np.zeros(0, dtype=np.int64)  # by user id: when it last took one; _NEVER: full
        self._ids: dict[Hashable, int] = {}  # keys and users not given as ints, interned
        self.n_considered = 0
        self.n_chosen = 0

    def choose(
        self,
        t_ms: np.ndarray,
        pair_keys: Sequence[Hashable] | np.ndarray,
        predicted_m: np.ndarray,
        sigma_at_prediction_m: np.ndarray,
        users: tuple[Sequence[Hashable] | np.ndarray, Sequence[Hashable] | np.ndarray] | None = None,
    ) -> np.ndarray:
        """Boolean mask of the readings to apply. ``pair_keys[i]`` identifies reading i's unordered pair and
        model (``pair_key``, or an int64 array from ``pair_keys``); ``predicted_m`` is the filters' distance
        between the two users; ``sigma_at_prediction_m`` is the model's range standard deviation at that
        distance; ``users`` the two users of each reading (None: no user's allowance applies; ints: user ids
        >= 0). The chosen pairs and users start their cooldowns. The gates are vectorised and the cooldowns
        one compiled pass over the readings that pass them: a busy building has thousands a call."""
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
        keys = pair_keys if isinstance(pair_keys, np.ndarray) else self._interned(pair_keys)
        keys = np.asarray(keys, dtype=np.int64)
        latest = latest_per_pair(t_ms, keys)
        self.n_considered += int(latest.size)
        gated = latest[
            (predicted_m[latest] <= p.select_range_m) & (sigma_at_prediction_m[latest] <= p.max_sigma_m)
        ]
        if users is None:
            user_a = user_b = np.full(n, -1, dtype=np.int64)
        else:  # the most informative first: a user's allowance goes to the first it takes
            gated = gated[np.argsort(sigma_at_prediction_m[gated], kind="stable")]
            user_a, user_b = (self._user_ids(u) for u in users)
            self._grow(int(max(user_a.max(), user_b.max())) + 1)
        if gated.size:
            self._pairs.make_room(gated.size)
            n_chosen, n_new = _choose(
                gated, t_ms, keys, user_a, user_b, self._pairs.keys, self._pairs.last_t_ms,
                self._left, self._since, p.pair_cooldown_ms, p.user_burst, p.user_rate_per_s, chosen,
            )  # fmt: skip
            self.n_chosen += n_chosen
            self._pairs.count += n_new
        return chosen

    def _interned(self, values: Sequence[Hashable]) -> np.ndarray:
        ids = self._ids
        return np.array([ids.setdefault(v, len(ids)) for v in values], dtype=np.int64)

    def _user_ids(self, values: Sequence[Hashable] | np.ndarray) -> np.ndarray:
        if isinstance(values, np.ndarray) and values.dtype.kind in "iu":
            ids = values.astype(np.int64, copy=False)
            if ids.size and ids.min() < 0:
                raise ValueError("user ids must be >= 0")
            return ids
        return self._interned(list(values))

    def _grow(self, n_users: int) -> None:
        if n_users > self._since.size:
            more = max(n_users, 2 * self._since.size) - self._since.size
            self._left = np.concatenate([self._left, np.zeros(more)])
            self._since = np.concatenate([self._since, np.full(more, _NEVER, dtype=np.int64)])

    def __len__(self) -> int:
        """Pairs with a remembered cooldown."""
        return self._pairs.count

    def forget_before(self, t_ms: int) -> None:
        """Drop cooldowns that ended before ``t_ms`` (bounded memory in a long-running building)."""
        horizon = t_ms - self.params.pair_cooldown_ms
        self._pairs.keep(self._pairs.last_t_ms >= horizon)
        full = t_ms - self.params.user_burst / self.params.user_rate_per_s * 1e3  # buckets full again
        self._since[self._since < full] = _NEVER


_NEVER = np.iinfo(np.int64).min
"""A user's last encounter time when its allowance is full (never taken one, or forgotten)."""
_EMPTY = np.iinfo(np.int64).min
"""A free entry of the pair table (pair keys are >= 0)."""


class _PairTable:
    """Open addressing over int64 pair keys (linear probing, at most half full): each pair's last encounter
    time, as arrays a compiled call reads and writes (and a snapshot pickles as two blocks)."""

    def __init__(self, capacity: int = 64) -> None:
        self.keys = np.full(capacity, _EMPTY, dtype=np.int64)
        self.last_t_ms = np.zeros(capacity, dtype=np.int64)
        self.count = 0

    def make_room(self, more: int) -> None:
        """Room for ``more`` new pairs with the table at most half full."""
        need = self.count + more
        if 2 * need > self.keys.size:
            capacity = self.keys.size
            while 2 * need > capacity:
                capacity *= 2
            self._rebuild(np.ones(self.keys.size, dtype=bool), capacity)

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the pairs where ``mask`` (by table entry) holds."""
        self._rebuild(mask, self.keys.size)

    def _rebuild(self, mask: np.ndarray, capacity: int) -> None:
        used = mask & (self.keys != _EMPTY)
        keys, times = self.keys[used], self.last_t_ms[used]
        self.keys = np.full(capacity, _EMPTY, dtype=np.int64)
        self.last_t_ms = np.zeros(capacity, dtype=np.int64)
        _insert_all(self.keys, self.last_t_ms, keys, times)
        self.count = int(keys.size)


@njit(cache=True, nogil=True)
def _slot(table: np.ndarray, key: np.int64) -> int:
    """Where ``key`` is in the table, or the free entry where it would go."""
    mask = table.size - 1  # a power of two
    i = home_slot(key, mask)
    while table[i] != _EMPTY and table[i] != key:
        i = (i + 1) & mask
    return i


@njit(cache=True, nogil=True)
def _insert_all(table: np.ndarray, values: np.ndarray, keys: np.ndarray, times: np.ndarray) -> None:
    for k in range(keys.size):
        i = _slot(table, keys[k])
        table[i] = keys[k]
        values[i] = times[k]


@njit(cache=True, nogil=True)
def _allowance(
    left: np.ndarray, since: np.ndarray, user: int, t: np.int64, burst: float, rate: float
) -> float:
    """The encounters ``user`` may still take at ``t`` (its bucket refilled since it last took one; a
    reading older than that refills nothing)."""
    if since[user] == _NEVER:
        return burst
    return float(min(burst, left[user] + max(t - since[user], 0) * rate / 1e3))


@njit(cache=True, nogil=True)
def _choose(
    gated: np.ndarray,
    t_ms: np.ndarray,
    keys: np.ndarray,
    user_a: np.ndarray,
    user_b: np.ndarray,
    table: np.ndarray,
    last_t_ms: np.ndarray,
    left: np.ndarray,
    since: np.ndarray,
    cooldown_ms: int,
    burst: float,
    rate: float,
    chosen: np.ndarray,
) -> tuple[int, int]:
    """The cooldowns over the gated readings, in order: a reading is chosen when its pair's last encounter
    is ``cooldown_ms`` behind it and both its users (unless -1: none) have an encounter left; the chosen
    start their cooldowns. How many were chosen, and how many of their pairs are new to the table."""
    n = 0
    new = 0
    for g in range(gated.size):
        i = gated[g]
        t = t_ms[i]
        at = _slot(table, keys[i])
        if table[at] == keys[i] and t - last_t_ms[at] < cooldown_ms:
            continue
        a, b = user_a[i], user_b[i]
        if a >= 0:
            left_a = _allowance(left, since, a, t, burst, rate)
            left_b = _allowance(left, since, b, t, burst, rate)
            if min(left_a, left_b) < 1.0:
                continue
            left[a], since[a] = left_a - 1.0, t
            left[b], since[b] = left_b - 1.0, t
        if table[at] != keys[i]:
            table[at] = keys[i]
            new += 1
        last_t_ms[at] = t
        chosen[i] = True
        n += 1
    return n, new


def latest_per_pair(t_ms: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Indices, in increasing order, of each pair's latest reading (the last of equal times): the only
    reading of a pair ``EncounterSelector.choose`` considers, so a caller may narrow its input to them.
    ``keys`` are pair keys (int64 >= 0); one pass over a hash table of them, not a sort of the readings."""
    keys = np.asarray(keys, dtype=np.int64)
    if keys.size == 0:
        return np.zeros(0, dtype=np.int64)
    latest: np.ndarray = _latest(np.asarray(t_ms, dtype=np.int64), keys)
    return latest


@njit(cache=True, nogil=True)
def _latest(t_ms: np.ndarray, keys: np.ndarray) -> np.ndarray:
    capacity = 16
    while capacity < 2 * keys.size:
        capacity *= 2
    table = np.full(capacity, _EMPTY, dtype=np.int64)
    best = np.empty(capacity, dtype=np.int64)
    n = 0
    for i in range(keys.size):
        at = _slot(table, keys[i])
        if table[at] != keys[i]:
            table[at] = keys[i]
            best[at] = i
            n += 1
        elif t_ms[i] >= t_ms[best[at]]:  # later, or as late and after it
            best[at] = i
    out = np.empty(n, dtype=np.int64)
    j = 0
    for at in range(capacity):
        if table[at] != _EMPTY:
            out[j] = best[at]
            j += 1
    out.sort()
    return out


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


class ReadingCarrier(Protocol):
    """How a reading is placed in time on its users (the tracker's side of ``choose_readings``): each slot's
    last event and a bound on its walk since a time, its guessed walk ahead of its last report, and its own
    steps since a time for the users named by their detector ids."""

    @property
    def last_t_ms(self) -> np.ndarray: ...
    def reach(self, slots: np.ndarray, t_ms: np.ndarray) -> np.ndarray: ...
    def extrapolated(
        self, slots: np.ndarray, t_ms: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
    def carried_since(
        self, user_ids: np.ndarray, which: np.ndarray, t_ms: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
    def carry_variance(self, walked_m: np.ndarray) -> np.ndarray: ...


def choose_readings(
    means_of: Callable[[np.ndarray], np.ndarray],
    detector: EncounterDetector,
    selector: EncounterSelector,
    found: DetectionArrays,
    slot_a: np.ndarray,
    slot_b: np.ndarray,
    carrier: ReadingCarrier,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The selector's choice among detections of tracked users (indices into ``found``), from the filters'
    current estimates placed at the detections' times, with each chosen one's offset and carry variance for
    ``DynamicSlam.observe_encounters``, and where the two were then (x_a, y_a, x_b, y_b: the filters'
    estimates before the encounter, at its time). ``means_of(slots)``: the filters' weighted means of these
    slots.

    Beyond the paper, which applies an encounter as it happens: a batch may span up to a minute and its
    encounters are applied after its steps, so each is carried from its time to now through both users'
    dead reckoning (``carrier.carried_since``); one older than either user's trail is left out. A peer whose
    phone has not yet reported up to the reading (its batch comes later: one reading in two on the simulated
    crowd, ~0.5 s behind) is guessed there at its recent velocity, with half the guess as its sigma
    (``carrier.extrapolated``; not at all after 5 s of silence). A busy call has thousands of readings: they
    are first narrowed to those the selector would consider (each pair's latest) and could choose (within
    its range of each other once either user's walk since, or its guessed walk beyond its last report, is
    allowed for), and only the users of those who walked after them are carried back step by step."""
    keys = pair_keys(found.user_a, found.user_b, found.model)
    latest = latest_per_pair(found.t_ms, keys)  # a busy call's readings are mostly repeats of their pairs
    n = latest.size
    t = found.t_ms[latest]
    sa, sb = slot_a[latest], slot_b[latest]
    slots, index = unique_ints_inverse(np.concatenate([sa, sb]))
    means = means_of(slots)
    mean_a, mean_b = means[index[:n]], means[index[n:]]
    delta_now = mean_a - mean_b  # of each pair's latest reading, as everything below
    ahead_a, guess_a, heard_a = carrier.extrapolated(sa, t)
    ahead_b, guess_b, heard_b = carrier.extrapolated(sb, t)
    bound = np.hypot(delta_now[:, 0], delta_now[:, 1])
    bound -= carrier.reach(sa, t) + np.hypot(ahead_a[:, 0], ahead_a[:, 1])
    bound -= carrier.reach(sb, t) + np.hypot(ahead_b[:, 0], ahead_b[:, 1])
    # a reading can be chosen only where its model's range sigma passes the selector's gate: for WiFi that is
    # ~2.3 m, well inside the selection range
    limit = np.full(int(found.model.max()) + 1, selector.params.select_range_m)
    for model in unique_ints(found.model[latest]):
        limit[model] = detector.range_model(int(model)).sigma_reach(
            selector.params.max_sigma_m, selector.params.select_range_m
        )
    near = np.flatnonzero((bound <= limit[found.model[latest]]) & heard_a & heard_b)
    c = near.size
    # only users who reported steps after a reading are carried back
    t2 = np.concatenate([t[near], t[near]])
    rows = np.flatnonzero(carrier.last_t_ms[np.concatenate([sa[near], sb[near]])] > t2)
    ids, who = unique_ints_inverse(
        np.concatenate([found.user_a[latest[near]], found.user_b[latest[near]]])[rows]
    )
    shift, walked, placeable = np.zeros((2 * c, 2)), np.zeros(2 * c), np.ones(2 * c, dtype=bool)
    if rows.size:
        shift[rows], walked[rows], placeable[rows] = carrier.carried_since(ids, who, t2[rows])
    ok = np.flatnonzero(placeable[:c] & placeable[c:])
    kept = near[ok]  # among the latest readings
    candidates = latest[kept]
    # a user's position then is where it is now minus its walk since, or plus its guessed walk beyond
    offset = (shift[:c] - shift[c:])[ok] - (ahead_a - ahead_b)[kept]
    then_a = mean_a[kept] - shift[:c][ok] + ahead_a[kept]
    then_b = mean_b[kept] - shift[c:][ok] + ahead_b[kept]
    carry_var = (carrier.carry_variance(walked[:c]) + carrier.carry_variance(walked[c:]))[ok]
    carry_var += (guess_a + guess_b)[kept]
    delta = delta_now[kept] - offset
    predicted = np.hypot(delta[:, 0], delta[:, 1])
    sigma = np.empty(candidates.size)
    models = found.model[candidates]
    for model in unique_ints(models):
        at = models == model
        sigma[at] = np.sqrt(detector.range_model(int(model)).variance_at_distance(predicted[at]))
    chosen = selector.choose(
        found.t_ms[candidates],
        keys[candidates],
        predicted,
        sigma,
        (found.user_a[candidates], found.user_b[candidates]),
    )
    if len(selector) > 100_000:
        selector.forget_before(int(found.t_ms.max()))
    return candidates[chosen], offset[chosen], carry_var[chosen], np.hstack([then_a, then_b])[chosen]
