"""A building's recent WiFi scans as arrays, with the per-AP inverted index the compiled encounter search
walks (``slam_core.encounters.search``): room is made, forgotten scans dropped and the index rebuilt
here, in Python, between the kernel's calls."""

from __future__ import annotations

import numpy as np

from slam_core.encounters.models import DetectionParams
from slam_core.encounters.search import (
    COUNT,
    HEAD,
    META_SIZE,
    N_LATE,
    NEWEST,
    NO_TIME,
    detect_scans,
    relink,
)


def _grown(array: np.ndarray, size: int, fill: float | int) -> np.ndarray:
    """``array`` with its first axis at least ``size`` (doubling), new rows set to ``fill``."""
    if array.shape[0] >= size:
        return array
    bigger = np.full((max(size, 2 * array.shape[0]), *array.shape[1:]), fill, dtype=array.dtype)
    bigger[: array.shape[0]] = array
    return bigger


class ScanStore:
    """A building's recent WiFi scans as arrays, in order of arrival, with a per-AP inverted index through
    their strongest N APs (``kernels.wifi_encounters``). Forgotten scans are dropped when the arrays fill."""

    def __init__(self, strongest_n: int, capacity: int = 1024) -> None:
        self.meta = np.zeros(META_SIZE, dtype=np.int64)
        self.meta[NEWEST] = NO_TIME
        self.t = np.zeros(capacity, dtype=np.int64)
        self.user = np.zeros(capacity, dtype=np.int64)
        self.top_ap = np.full((capacity, strongest_n), -1, dtype=np.int64)
        self.top_rss = np.zeros((capacity, strongest_n))
        self.link = np.full((capacity, strongest_n), -1, dtype=np.int64)
        self.fresh_lo = np.zeros(capacity, dtype=np.int64)
        self.fresh_hi = np.zeros(capacity, dtype=np.int64)
        self.late = np.zeros(capacity, dtype=np.int64)
        self.visited = np.zeros(capacity, dtype=np.int64)
        self.fresh_ap = np.zeros(4 * capacity, dtype=np.int64)
        self.fresh_rss = np.zeros(4 * capacity)
        self.fresh_used = 0
        self.ap_head = np.full(256, -1, dtype=np.int64)
        self.top_mark = np.zeros(256, dtype=np.int64)
        self.mark = np.zeros(256, dtype=np.int64)
        self.value = np.zeros(256)

    @property
    def live(self) -> int:
        return int(self.meta[COUNT] - self.meta[HEAD])

    def _compact(self) -> None:
        """Move the live scans (and their fresh APs) to the front and rebuild the index."""
        head, count = int(self.meta[HEAD]), int(self.meta[COUNT])
        if head == 0:
            return
        n = count - head
        for name in ("t", "user", "top_ap", "top_rss", "fresh_lo", "fresh_hi"):
            array = getattr(self, name)
            array[:n] = array[head:count]
        base = int(self.fresh_lo[0]) if n else self.fresh_used
        used = self.fresh_used - base
        self.fresh_ap[:used] = self.fresh_ap[base : self.fresh_used]
        self.fresh_rss[:used] = self.fresh_rss[base : self.fresh_used]
        self.fresh_lo[:n] -= base
        self.fresh_hi[:n] -= base
        self.fresh_used = used
        late = self.late[: self.meta[N_LATE]]
        late = late[late >= head] - head
        self.late[: late.size] = late
        self.meta[N_LATE] = late.size
        late_flag = np.zeros(n, dtype=np.bool_)
        late_flag[late] = True
        self.visited[:] = 0
        self.meta[HEAD] = 0
        self.meta[COUNT] = n
        relink(self.top_ap, self.link, self.ap_head, late_flag, n)

    def _make_room(self, n_scans: int, n_fresh: int, n_aps: int) -> None:
        if self.meta[COUNT] + n_scans > self.t.size or self.fresh_used + n_fresh > self.fresh_ap.size:
            self._compact()
        need = int(self.meta[COUNT]) + n_scans
        for name, fill in (
            ("t", 0), ("user", 0), ("top_ap", -1), ("top_rss", 0.0), ("link", -1), ("fresh_lo", 0),
            ("fresh_hi", 0), ("late", 0), ("visited", 0),
        ):  # fmt: skip
            setattr(self, name, _grown(getattr(self, name), need, fill))
        self.fresh_ap = _grown(self.fresh_ap, self.fresh_used + n_fresh, 0)
        self.fresh_rss = _grown(self.fresh_rss, self.fresh_used + n_fresh, 0.0)
        self.ap_head = _grown(self.ap_head, n_aps, -1)
        self.top_mark = _grown(self.top_mark, n_aps, 0)
        self.mark = _grown(self.mark, n_aps, 0)
        self.value = _grown(self.value, n_aps, 0.0)

    def add(
        self,
        t_ms: np.ndarray,
        user: np.ndarray,
        top_ap: np.ndarray,
        top_rss: np.ndarray,
        fresh_offsets: np.ndarray,
        fresh_ap: np.ndarray,
        fresh_rss: np.ndarray,
        n_aps: int,
        params: DetectionParams,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Store scans (in arrival order) and compare each with the live scans before it; returns the
        passing pairs as (t, index among these scans, the other's user, feature)."""
        self._make_room(t_ms.size, fresh_ap.size, n_aps)
        base = self.fresh_used
        self.fresh_ap[base : base + fresh_ap.size] = fresh_ap
        self.fresh_rss[base : base + fresh_ap.size] = fresh_rss
        self.fresh_used += fresh_ap.size
        by_fingerprint = params.wifi_model == "wifi-fingerprint"
        out_t, out_new, out_other, out_f = detect_scans(
            self.meta, self.t, self.user, self.top_ap, self.top_rss, self.link, self.fresh_lo,
            self.fresh_hi, self.fresh_ap, self.fresh_rss, self.ap_head, self.late, self.visited,
            self.top_mark, self.mark, self.value, t_ms, user, top_ap, top_rss, base + fresh_offsets[:-1],
            base + fresh_offsets[1:], params.scan_pair_window_ms, params.retention_ms, params.late_scan_ms,
            by_fingerprint,
            params.fingerprint.threshold_db if by_fingerprint else params.wifi.threshold_db,
            params.wifi.min_common, params.fingerprint.floor_dbm,
        )  # fmt: skip
        return out_t, out_new, self.user[out_other], out_f
