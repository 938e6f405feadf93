"""Who is in which zone: entries, exits and dwells decided with each user's uncertainty.

Beyond both papers. Platforms that offer zones (geofences) decide "inside" from one point, so an estimate
near a boundary flickers in and out and every flicker is a false event. Here a user enters a zone when the
probability that it is inside (``slam_core.zones.geometry.inside_shares``) reaches ``enter_probability``,
and leaves when it falls to ``exit_probability``: between the two the user stays as it was (hysteresis). A
dwell fires once, when the user has been inside a zone for its ``dwell_ms``. A zone of another floor has
probability 0, so a change of floor leaves the old floor's zones. Pure numerics: arrays by the caller's user
rows (the filters' slots) and zone indices.

An event is told when it is sure, and stamped with when it happened: the last time the probability crossed
one half (``stamp_probability``) before it reached the threshold, the moment the user most likely crossed
the outline. Told without the stamp, an entry decided at 0.8 would be a second or two late, and every
visit shorter by the time the thresholds take, which loses the short visits a shop front sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

ENTER, EXIT, DWELL = 0, 1, 2
KINDS = ("enter", "exit", "dwell")


@dataclass(frozen=True)
class ZoneParams:
    enter_probability: float = 0.8
    """A user enters a zone when at least this share of its particles' weight lies inside."""
    exit_probability: float = 0.2
    """... and leaves it when at most this share does: an estimate hovering at a boundary, inside with
    probability about one half, neither enters nor leaves."""
    stamp_probability: float = 0.5
    """An event is stamped with the last time the probability crossed this share on its way to the
    threshold."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.exit_probability < self.stamp_probability < self.enter_probability <= 1.0:
            raise ValueError(
                "zone thresholds need 0 <= exit_probability < stamp_probability < enter_probability <= 1"
            )


@dataclass(frozen=True)
class ZoneEvents:
    """Events of one update, in user order then zone order: the user row, the zone index, the kind
    (``ENTER``, ``EXIT``, ``DWELL``), when it happened (ms: the stamp), the probability inside when it was
    decided, and when that was (the user's time in the update)."""

    row: np.ndarray
    zone: np.ndarray
    kind: np.ndarray
    t_ms: np.ndarray
    probability: np.ndarray
    told_ms: np.ndarray

    def __len__(self) -> int:
        return int(self.row.size)


class ZonePresence:
    """Each (user row, zone): inside or not, since when (ms), whether its dwell has fired, whether the
    probability was at least ``stamp_probability`` at the last update, and when it last crossed it."""

    FIELDS = ("inside", "since_ms", "dwelled", "likely", "crossed_ms")

    def __init__(self, params: ZoneParams | None = None) -> None:
        self.params = params or ZoneParams()
        self.inside = np.zeros((0, 0), dtype=np.bool_)
        self.since_ms = np.zeros((0, 0), dtype=np.int64)
        self.dwelled = np.zeros((0, 0), dtype=np.bool_)
        self.likely = np.zeros((0, 0), dtype=np.bool_)
        self.crossed_ms = np.zeros((0, 0), dtype=np.int64)

    def _room(self, rows: int, zones: int) -> None:
        have_rows, have_zones = self.inside.shape
        if rows <= have_rows and zones <= have_zones:
            return
        shape = (have_rows if rows <= have_rows else max(rows, 2 * have_rows), max(zones, have_zones))
        for name in self.FIELDS:
            old = getattr(self, name)
            new = np.zeros(shape, dtype=old.dtype)
            new[: old.shape[0], : old.shape[1]] = old
            setattr(self, name, new)

    def clear_rows(self, rows: np.ndarray) -> None:
        """Users that left (their rows will serve others): inside nothing, without events."""
        rows = np.asarray(rows, dtype=np.int64)
        rows = rows[rows < self.inside.shape[0]]
        self.inside[rows] = False
        self.dwelled[rows] = False
        self.likely[rows] = False

    def renumber_zones(self, keep: np.ndarray) -> None:
        """The zones were renumbered: column ``k`` of the new set is old column ``keep[k]`` (-1: a new zone,
        nobody inside yet). Deleting a zone ends its visits without events (the caller closes them)."""
        keep = np.asarray(keep, dtype=np.int64)
        rows = self.inside.shape[0]
        for name in self.FIELDS:
            old = getattr(self, name)
            new = np.zeros((rows, keep.size), dtype=old.dtype)
            have = (keep >= 0) & (keep < old.shape[1])
            new[:, have] = old[:, keep[have]]
            setattr(self, name, new)

    def update(
        self, rows: np.ndarray, t_ms: np.ndarray, shares: np.ndarray, dwell_ms: np.ndarray
    ) -> ZoneEvents:
        """The users ``rows`` at times ``t_ms``, with their probabilities inside each zone ``shares`` (U, Z)
        and the zones' dwell times (negative: none): the events they cause."""
        rows = np.asarray(rows, dtype=np.int64)
        shares = np.asarray(shares, dtype=np.float64).reshape(rows.size, -1)
        dwell_ms = np.asarray(dwell_ms, dtype=np.int64)
        if dwell_ms.size != shares.shape[1] or np.asarray(t_ms).size != rows.size:
            raise ValueError("one time per user and one dwell time per zone")
        if rows.size and (rows.min() < 0 or np.unique(rows).size != rows.size):
            raise ValueError("user rows must be distinct and non-negative")
        self._room(int(rows.max()) + 1 if rows.size else 0, shares.shape[1])
        p = self.params
        out = _transitions(
            rows,
            np.asarray(t_ms, dtype=np.int64),
            shares,
            dwell_ms,
            self.inside,
            self.since_ms,
            self.dwelled,
            self.likely,
            self.crossed_ms,
            p.enter_probability,
            p.exit_probability,
            p.stamp_probability,
        )
        return ZoneEvents(*out)


@njit(cache=True, nogil=True)
def _transitions(
    rows: np.ndarray,
    t_ms: np.ndarray,
    shares: np.ndarray,
    dwell_ms: np.ndarray,
    inside: np.ndarray,
    since_ms: np.ndarray,
    dwelled: np.ndarray,
    likely: np.ndarray,
    crossed_ms: np.ndarray,
    enter_p: float,
    exit_p: float,
    stamp_p: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n_users, n_zones = shares.shape
    cap = 2 * n_users * n_zones
    e_row = np.empty(cap, dtype=np.int64)
    e_zone = np.empty(cap, dtype=np.int64)
    e_kind = np.empty(cap, dtype=np.int64)
    e_t = np.empty(cap, dtype=np.int64)
    e_p = np.empty(cap)
    e_told = np.empty(cap, dtype=np.int64)
    n = 0
    for k in range(n_users):
        r, t = rows[k], t_ms[k]
        for z in range(n_zones):
            p = shares[k, z]
            if (p >= stamp_p) != likely[r, z]:  # the probability crossed one half now
                likely[r, z] = p >= stamp_p
                crossed_ms[r, z] = t
            if inside[r, z]:
                if p <= exit_p:
                    inside[r, z] = False
                    e_row[n], e_zone[n], e_kind[n], e_t[n], e_p[n], e_told[n] = (
                        r,
                        z,
                        1,
                        crossed_ms[r, z],
                        p,
                        t,
                    )
                    n += 1
                    continue
            elif p >= enter_p:
                inside[r, z] = True
                since_ms[r, z] = crossed_ms[r, z]
                dwelled[r, z] = False
                e_row[n], e_zone[n], e_kind[n], e_t[n], e_p[n], e_told[n] = r, z, 0, crossed_ms[r, z], p, t
                n += 1
            if inside[r, z] and not dwelled[r, z] and dwell_ms[z] >= 0 and t - since_ms[r, z] >= dwell_ms[z]:
                dwelled[r, z] = True
                e_row[n], e_zone[n], e_kind[n] = r, z, 2
                e_t[n], e_p[n], e_told[n] = since_ms[r, z] + dwell_ms[z], p, t
                n += 1
    return (
        e_row[:n].copy(),
        e_zone[:n].copy(),
        e_kind[:n].copy(),
        e_t[:n].copy(),
        e_p[:n].copy(),
        e_told[:n].copy(),
    )
