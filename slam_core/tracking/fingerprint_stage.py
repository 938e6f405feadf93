"""The tracker's fingerprint stage (beyond the papers, in dynamicslam mode): each tracked user's latest scan
that the crowd's WiFi fingerprint map can place, carried to now along the user's steps, is a robust position
fix; the scans of confident users join the map. The stage owns the crowd's fingerprint maps, one per floor,
which also place phones started without a fix (the tracker's cold starts), take signal-map builds' radio
maps, and say how well each floor explains a scan (``floor_evidence``, for ``slam_core.tracking.floors``).
Pure numerics.
"""

from __future__ import annotations

import math

import numpy as np

from slam_core.crowd.fingerprints import (
    NOBODY,
    SURVEY_OWNER,
    CrowdFingerprints,
    FingerprintParams,
    Place,
    Scan,
)
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.tracking.batches import EstimateRow, UserBatch, UserReport
from slam_core.tracking.carry import carried_since
from slam_core.tracking.floors import FloorParams
from slam_core.tracking.trails import Trails, UserTrack

FLOOR_NEIGHBOURS = 8
"""A floor's references near the user that its evidence weighs (the nearest in signal space among them)."""


class FingerprintStage:
    def __init__(
        self, params: FingerprintParams, stale_ap_ms: int, floors: FloorParams | None = None
    ) -> None:
        self.params = params
        self.floors = floors or FloorParams()
        self.stale_ap_ms = stale_ap_ms
        self.maps: dict[int, CrowdFingerprints] = {}
        # The signal-map build whose radio map the maps hold (None: none loaded).
        self.radio_map_id: str | None = None

    def map_of(self, level: int) -> CrowdFingerprints:
        """The floor's fingerprint map (empty until its users' scans join)."""
        found = self.maps.get(level)
        if found is None:
            found = self.maps[level] = CrowdFingerprints(self.params)
        return found

    def load_radio_map(
        self,
        map_id: str,
        xy: np.ndarray,
        bssids: list[list[str]],
        rss: list[np.ndarray],
        t_ms: np.ndarray,
        levels: np.ndarray | None = None,
    ) -> int:
        """Add the scans of a signal-map build (SignalSLAM's positions) to their floors' maps (``levels``, one
        per scan; None: all on floor 0), owned by no user; returns how many joined (the map's per-cell bound
        applies). A map already loaded (by ``map_id``, which snapshots keep) is not loaded again."""
        if map_id == self.radio_map_id:
            return 0
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        levels = np.zeros(xy.shape[0], dtype=np.int64) if levels is None else np.asarray(levels)
        if not (len(bssids) == len(rss) == xy.shape[0] == len(t_ms) == levels.size) or not np.all(
            np.isfinite(xy)
        ):
            raise ValueError("radio map: one finite position, BSSID list, RSS array, time and floor per scan")
        added = sum(
            self.map_of(int(levels[i])).add(
                SURVEY_OWNER, xy[i], bssids[i], np.asarray(rss[i], dtype=np.float64), int(t_ms[i])
            )
            for i in range(xy.shape[0])
        )
        self.radio_map_id = map_id
        return added

    def floor_evidence(
        self,
        levels: tuple[int, ...],
        owner: int,
        bssids: list[str],
        rss: np.ndarray,
        centre: np.ndarray | None,
    ) -> np.ndarray:
        """Per level, the log-likelihood that the scan was taken on it; NaN where the floor's map knows
        nothing there. Anywhere on the floor (``centre`` None: a phone not yet placed): -d^2 / (2 s^2), d the
        union distance (dB) to the floor map's nearest reference of another user, s
        ``FloorParams.radio_sigma_db``. Near a tracked user's estimate ``centre``: the floor's references
        within ``FloorParams.radio_radius_m`` as a kernel estimate of the scan's likelihood there,
        log(sum_r w_r exp(-d_r^2 / (2 s^2)) / sum_r w_r), w_r = exp(-r^2 / (2 rho^2)) by the reference's
        distance r from the estimate, rho ``FloorParams.radio_place_sigma_m``: a floor whose crowd never
        walked where the user is says nothing, and how close its crowd came does not count for or against
        it, only how its scans there look (the best reference less its distance, as first built, let the
        floor above that was walked just there win: 97.5 % of the six-floor mall's estimates on the right
        floor against 98.9 %; docs/experiments.md)."""
        fp = self.floors
        out = np.full(len(levels), math.nan)
        for i, level in enumerate(levels):
            found = self.maps.get(level)
            if found is None or len(found) < self.params.min_references:
                continue
            if centre is None:
                _, d = found.nearby(owner, bssids, rss, np.zeros(2), math.inf, 1)
                if d.size:
                    out[i] = -0.5 * (d[0] / fp.radio_sigma_db) ** 2
                continue
            xy, d = found.nearby(owner, bssids, rss, centre, fp.radio_radius_m, FLOOR_NEIGHBOURS)
            if d.size:
                r2 = ((xy - centre) ** 2).sum(axis=1)
                w = np.exp(-0.5 * r2 / fp.radio_place_sigma_m**2)
                like = np.exp(-0.5 * (d / fp.radio_sigma_db) ** 2)
                out[i] = float(np.log(max(np.sum(w * like) / np.sum(w), 1e-300)))
        return out

    def candidates(
        self, level: int, bssids: list[str], rss: np.ndarray, max_spread_m: float
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``CrowdFingerprints.candidates`` of a phone not yet started, on the floor's map."""
        found = self.maps.get(level)
        return None if found is None else found.candidates(NOBODY, bssids, rss, max_spread_m)

    def fix(
        self,
        filters: DynamicSlam,
        batches: list[UserBatch],
        users: dict[str, UserTrack],
        rows: dict[str, EstimateRow],
        reports: dict[str, UserReport],
        trails: Trails,
    ) -> None:
        """Each fresh scan of a tracked user, carried to now with the user's dead reckoning since it (its
        steps in ``trails``), for ``apply``. ``rows``: the current estimates of the batches' tracked users
        with scans."""
        names, located = [], []
        scanning = [b for b in batches if b.user in rows]
        if not scanning:
            return
        tracks = [users[b.user] for b in scanning]
        counts = [b.scan_t.size for b in scanning]
        carried, _, _ = carried_since(  # every scan of the call carried to now in one search
            trails,
            np.repeat(np.array([u.slot for u in tracks], dtype=np.int64), counts),
            np.repeat(np.array([u.last_t_ms for u in tracks], dtype=np.int64), counts),
            np.concatenate([b.scan_t for b in scanning]),
        )
        first = 0
        for b, u in zip(scanning, tracks, strict=True):
            row = rows[b.user]
            scans = []
            for c in range(b.scan_t.size):
                t, bssids, rss = b.fresh_scan(c, self.stale_ap_ms)
                scans.append(Scan(bssids, rss, carried[first + c], t))
            first += b.scan_t.size
            cov = np.array([[row.cov[0], row.cov[1]], [row.cov[1], row.cov[2]]])
            names.append(b.user)
            # a scan joins its floor's map only when the filter is sure of the floor
            sure = row.floor_probability >= self.floors.join_confidence
            located.append((u.slot, u.number, np.array([row.x, row.y]), cov, scans, row.floor, sure))
        got = self.apply(filters, located)
        for name, fixed in zip(names, got, strict=True):
            if fixed is not None:
                reports[name].fingerprint_fixes += 1
                reports[name].fingerprint_fix = (float(fixed[0]), float(fixed[1]))

    def apply(
        self,
        filters: DynamicSlam,
        located: list[tuple[int, int, np.ndarray, np.ndarray, list[Scan], int, bool]],
    ) -> list[np.ndarray | None]:
        """For each (slot, owner, estimate now, its covariance, the user's scans of this call in time order,
        its floor, whether the filter is sure of that floor): the latest scan the floor's map can place,
        carried to now, is a robust fix (``DynamicSlam.observe_position_robust``, all of a call's fixes in one
        tracker call), then the confident users' scans join their floor's map
        (``CrowdFingerprints.fixes_and_places``). Returns each user's fix, or None."""
        params = self.params
        slots, fixes = [], []
        got: list[np.ndarray | None] = []
        places: list[tuple[int, Place]] = []
        results: list[tuple[np.ndarray | None, list[Place]]] = [(None, [])] * len(located)
        for level in dict.fromkeys(item[5] for item in located):  # each floor's map searched once
            mine = [i for i, item in enumerate(located) if item[5] == level]
            users = [(located[i][1], located[i][2], located[i][3], located[i][4]) for i in mine]
            for i, result in zip(mine, self.map_of(level).fixes_and_places(users), strict=True):
                results[i] = result
        for (slot, _, _, _, _, level, sure), (fix, joining) in zip(located, results, strict=True):
            if sure:
                places += [(level, p) for p in joining]
            got.append(fix)
            if fix is not None:
                slots.append(slot)
                fixes.append(fix)
        if slots:
            filters.observe_position_robust(
                np.array(slots, dtype=np.int64),
                np.array(fixes),
                params.sigma_m,
                params.outlier_probability,
                params.outlier_radius_m,
            )
        for level, place in places:
            self.map_of(level).add(place.owner, place.xy, place.bssids, place.rss, place.t_ms)
        return got
