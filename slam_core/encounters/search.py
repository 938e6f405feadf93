"""WiFi encounter candidates over a building's recent scans (DynamicSLAM Eq. 3, and our union-fingerprint
feature), compiled: one call handles every scan of a tracker call in arrival order.

The recent scans live in arrays (``slam_core.encounters.detection.ScanStore`` owns them): per scan its time,
user, strongest-N APs (interned ids, -1 padded) with their RSS, and its fresh APs as a slice of flat arrays.
The inverted index is a singly linked list per AP through the strongest-N entries, newest first
(``ap_head[ap]`` -> entry ``scan * N + k`` -> ``link[scan, k]`` -> ...). A scan's candidates are found by
walking its APs' lists, so its cost grows with the scans that share one of its APs inside the window, not
with the building's users.

A walk stops at the first entry older than ``t - window - late_ms``: every scan linked earlier (by arrival)
is older still, because a linked scan was at most ``late_ms`` behind the newest scan when it arrived. Scans
that arrive later than that (a phone's delayed batch) are not linked: they are kept in a short list that
every scan checks directly.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from slam_core.wifi.similarity import eq3, union_rms

# meta layout (int64): first live scan, scans stored, newest scan time, candidates compared, late scans
# listed, and a serial that stamps each new scan (never reused, so marks left in the scratch arrays by earlier
# scans cannot be mistaken for the current one's)
HEAD, COUNT, NEWEST, CANDIDATES, N_LATE, SERIAL = range(6)
META_SIZE = 6
NO_TIME = np.iinfo(np.int64).min


@njit(cache=True, nogil=True)
def _union_rms(
    fresh_lo: np.ndarray,
    fresh_hi: np.ndarray,
    fresh_ap: np.ndarray,
    fresh_rss: np.ndarray,
    j: int,
    n_own: int,
    own_sq: float,
    mark: np.ndarray,
    value: np.ndarray,
    stamp: int,
    floor: float,
) -> float:
    """The union-fingerprint distance between the marked scan's fresh APs (``value``: RSS floored; ``own_sq``
    its gains' sum of squares) and scan j's, gathered over j's entries only, so the marked scan's APs
    missing from j cost nothing to visit."""
    squares = 0.0
    dot = 0.0
    common = 0
    for e in range(fresh_lo[j], fresh_hi[j]):
        ap = fresh_ap[e]
        gain = max(fresh_rss[e], floor) - floor
        squares += gain * gain
        if mark[ap] == stamp:
            dot += (value[ap] - floor) * gain
            common += 1
    return union_rms(own_sq, squares, dot, n_own, fresh_hi[j] - fresh_lo[j], common)


@njit(cache=True, nogil=True)
def _push(buffer: np.ndarray, n: int, value: int) -> np.ndarray:
    if n == buffer.shape[0]:
        buffer = np.concatenate((buffer, np.empty(max(n, 16), dtype=buffer.dtype)))
    buffer[n] = value
    return buffer


# Like every compiled kernel it takes the store's arrays one by one: numba compiles plain arrays and
# scalars, so kernels over like state share the shape of their parameter lists.
@njit(cache=True, nogil=True)
def detect_scans(
    meta: np.ndarray,
    t: np.ndarray,
    user: np.ndarray,
    top_ap: np.ndarray,
    top_rss: np.ndarray,
    link: np.ndarray,
    fresh_lo: np.ndarray,
    fresh_hi: np.ndarray,
    fresh_ap: np.ndarray,
    fresh_rss: np.ndarray,
    ap_head: np.ndarray,
    late: np.ndarray,
    visited: np.ndarray,
    top_mark: np.ndarray,
    mark: np.ndarray,
    value: np.ndarray,
    new_t: np.ndarray,
    new_user: np.ndarray,
    new_top_ap: np.ndarray,
    new_top_rss: np.ndarray,
    new_fresh_lo: np.ndarray,
    new_fresh_hi: np.ndarray,
    window_ms: int,
    retention_ms: int,
    late_ms: int,
    by_fingerprint: bool,
    threshold: float,
    min_common: int,
    floor: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Store the new scans after the stored ones, in order, each compared first with the live scans before
    it. The caller has made room: the scan arrays (and ``late``, ``visited``) hold every new scan, the
    ``fresh_*`` arrays already hold the new scans' fresh APs at ``new_fresh_lo:new_fresh_hi`` (empty for
    Eq. 3), and ``ap_head``, ``top_mark``, ``mark`` and ``value`` cover every AP id.

    Returns the passing pairs as (t = the later scan's time, the new scan's index among this call's scans,
    the other's stored index, feature): per new scan, in the other's order of arrival."""
    n_top = top_ap.shape[1]
    out_t = np.empty(64, dtype=np.int64)
    out_new = np.empty(64, dtype=np.int64)
    out_other = np.empty(64, dtype=np.int64)
    out_f = np.empty(64, dtype=np.float64)
    n_out = 0
    candidates = np.empty(64, dtype=np.int64)
    for s in range(new_t.shape[0]):
        ts = new_t[s]
        head = meta[HEAD]
        count = meta[COUNT]
        newest = meta[NEWEST]
        lateness = newest - ts if newest != NO_TIME else 0
        if ts > newest:
            newest = ts
        horizon = newest - retention_ms
        while head < count and t[head] < horizon:  # forgotten in arrival order
            head += 1
        meta[SERIAL] += 1
        stamp = meta[SERIAL]
        for k in range(n_top):
            ap = new_top_ap[s, k]
            if ap < 0:
                break
            top_mark[ap] = stamp
        n_own = 0
        own_sq = 0.0
        if by_fingerprint:
            for e in range(new_fresh_lo[s], new_fresh_hi[s]):
                ap = fresh_ap[e]
                r = max(fresh_rss[e], floor)
                mark[ap] = stamp
                value[ap] = r
                own_sq += (r - floor) ** 2
                n_own += 1
        # candidates: live scans of other users within the window sharing one of the strongest N
        lo_t = ts - window_ms
        hi_t = ts + window_ms
        n_cand = 0
        for k in range(n_top):
            ap = new_top_ap[s, k]
            if ap < 0:
                break
            e = ap_head[ap]
            while e >= 0:
                j = e // n_top
                if j < head or t[j] < lo_t - late_ms:
                    break  # every scan linked before it is older still
                inside = lo_t <= t[j] <= hi_t and t[j] >= horizon
                if inside and visited[j] != stamp and user[j] != new_user[s]:
                    visited[j] = stamp
                    candidates = _push(candidates, n_cand, j)
                    n_cand += 1
                e = link[j, e - j * n_top]
        for q in range(meta[N_LATE]):
            j = late[q]
            if j < head or visited[j] == stamp or not (lo_t <= t[j] <= hi_t) or t[j] < horizon:
                continue
            if user[j] == new_user[s]:
                continue
            for k in range(n_top):
                ap = top_ap[j, k]
                if ap >= 0 and top_mark[ap] == stamp:
                    visited[j] = stamp
                    candidates = _push(candidates, n_cand, j)
                    n_cand += 1
                    break
        ordered = np.sort(candidates[:n_cand])
        meta[CANDIDATES] += n_cand
        for c in range(n_cand):
            j = ordered[c]
            if by_fingerprint:
                feature = _union_rms(
                    fresh_lo, fresh_hi, fresh_ap, fresh_rss, j, n_own, own_sq, mark, value, stamp, floor
                )
                passing = feature < threshold
            else:
                feature, common = eq3(new_top_ap[s], new_top_rss[s], top_ap[j], top_rss[j])
                passing = common >= min_common and feature < threshold
            if passing:
                if n_out == out_t.shape[0]:
                    out_t = np.concatenate((out_t, np.empty(n_out, dtype=np.int64)))
                    out_new = np.concatenate((out_new, np.empty(n_out, dtype=np.int64)))
                    out_other = np.concatenate((out_other, np.empty(n_out, dtype=np.int64)))
                    out_f = np.concatenate((out_f, np.empty(n_out, dtype=np.float64)))
                out_t[n_out] = max(ts, t[j])
                out_new[n_out] = s
                out_other[n_out] = j
                out_f[n_out] = feature
                n_out += 1
        # store the scan; link it into its APs' lists unless it arrived late
        i = count
        t[i] = ts
        user[i] = new_user[s]
        fresh_lo[i] = new_fresh_lo[s]
        fresh_hi[i] = new_fresh_hi[s]
        visited[i] = 0
        is_late = lateness > late_ms
        for k in range(n_top):
            ap = new_top_ap[s, k]
            top_ap[i, k] = ap
            top_rss[i, k] = new_top_rss[s, k]
            link[i, k] = -1
            if ap >= 0 and not is_late:
                link[i, k] = ap_head[ap]
                ap_head[ap] = i * n_top + k
        if is_late:
            late[meta[N_LATE]] = i
            meta[N_LATE] += 1
        meta[HEAD] = head
        meta[COUNT] = count + 1
        meta[NEWEST] = newest
    return out_t[:n_out], out_new[:n_out], out_other[:n_out], out_f[:n_out]


@njit(cache=True, nogil=True)
def relink(
    top_ap: np.ndarray, link: np.ndarray, ap_head: np.ndarray, late_flag: np.ndarray, count: int
) -> None:
    """Rebuild the per-AP lists of the first ``count`` stored scans (after the arrays were compacted);
    late scans stay unlinked."""
    n_top = top_ap.shape[1]
    ap_head[:] = -1
    for i in range(count):
        for k in range(n_top):
            ap = top_ap[i, k]
            link[i, k] = -1
            if ap >= 0 and not late_flag[i]:
                link[i, k] = ap_head[ap]
                ap_head[ap] = i * n_top + k
