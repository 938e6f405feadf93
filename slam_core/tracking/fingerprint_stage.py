"""The tracker's fingerprint stage (beyond the papers, in dynamicslam mode): each tracked user's latest scan
that the crowd's WiFi fingerprint map can place, carried to now along the user's steps, is a robust position
fix; the scans of confident users join the map. The stage owns the crowd's fingerprint map, which also places
phones started without a fix (the tracker's cold starts) and takes a signal-map build's radio map. Pure
numerics.
"""

from __future__ import annotations

import numpy as np

from slam_core.crowd.fingerprints import SURVEY_OWNER, CrowdFingerprints, FingerprintParams, Place, Scan
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.tracking.batches import EstimateRow, UserBatch, UserReport
from slam_core.tracking.carry import TrackTable, carried_since
from slam_core.tracking.trails import UserTrack


class FingerprintStage:
    def __init__(self, params: FingerprintParams, stale_ap_ms: int) -> None:
        self.params = params
        self.stale_ap_ms = stale_ap_ms
        self.map = CrowdFingerprints(params)
        # The signal-map build whose radio map the map holds (None: none loaded).
        self.radio_map_id: str | None = None

    def load_radio_map(
        self, map_id: str, xy: np.ndarray, bssids: list[list[str]], rss: list[np.ndarray], t_ms: np.ndarray
    ) -> int:
        """Add the scans of a signal-map build (SignalSLAM's positions) to the map, owned by no user; returns
        how many joined (the map's per-cell bound applies). A map already loaded (by ``map_id``, which
        snapshots keep) is not loaded again."""
        if map_id == self.radio_map_id:
            return 0
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not (len(bssids) == len(rss) == xy.shape[0] == len(t_ms)) or not np.all(np.isfinite(xy)):
            raise ValueError("radio map: one finite position, BSSID list, RSS array and time per scan")
        added = sum(
            self.map.add(SURVEY_OWNER, xy[i], bssids[i], np.asarray(rss[i], dtype=np.float64), int(t_ms[i]))
            for i in range(xy.shape[0])
        )
        self.radio_map_id = map_id
        return added

    def fix(
        self,
        engine: DynamicSlam,
        batches: list[UserBatch],
        users: dict[str, UserTrack],
        rows: dict[str, EstimateRow],
        reports: dict[str, UserReport],
    ) -> None:
        """Each fresh scan of a tracked user, carried to now with the user's dead reckoning since it, for
        ``apply``. ``rows``: the current estimates of the batches' tracked users with scans."""
        names, located = [], []
        scanning = [b for b in batches if b.user in rows]
        if not scanning:
            return
        tracks = [users[b.user] for b in scanning]
        counts = [b.scan_t.size for b in scanning]
        carried, _, _ = carried_since(  # every scan of the call carried to now in one search
            TrackTable.of(tracks),
            np.repeat(np.arange(len(tracks)), counts),
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
            located.append((u.slot, u.number, np.array([row.x, row.y]), cov, scans))
        got = self.apply(engine, located)
        for name, fixed in zip(names, got, strict=True):
            if fixed is not None:
                reports[name].fingerprint_fixes += 1
                reports[name].fingerprint_fix = (float(fixed[0]), float(fixed[1]))

    def apply(
        self, engine: DynamicSlam, located: list[tuple[int, int, np.ndarray, np.ndarray, list[Scan]]]
    ) -> list[np.ndarray | None]:
        """For each (slot, owner, estimate now, its covariance, the user's scans of this call in time order):
        the latest scan the map can place, carried to now, is a robust fix
        (``DynamicSlam.observe_position_robust``, all of a call's fixes in one engine call), then the
        confident users' scans join the map (``CrowdFingerprints.fix_and_places``). Returns each user's fix,
        or None."""
        params = self.params
        slots, fixes = [], []
        got: list[np.ndarray | None] = []
        places: list[Place] = []
        for slot, owner, xy, cov, scans in located:
            fix, joining = self.map.fix_and_places(owner, xy, cov, scans)
            places += joining
            got.append(fix)
            if fix is not None:
                slots.append(slot)
                fixes.append(fix)
        if slots:
            engine.observe_position_robust(
                np.array(slots, dtype=np.int64),
                np.array(fixes),
                params.sigma_m,
                params.outlier_probability,
                params.outlier_radius_m,
            )
        for place in places:
            self.map.add(place.owner, place.xy, place.bssids, place.rss, place.t_ms)
        return got
