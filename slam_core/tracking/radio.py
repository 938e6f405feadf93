"""The tracker's observations of identified signals (``slam_core.tracking.tracker.BuildingTracker`` calls them
in order): signature anchors inside each round of events (identified transmitters and signatures, placed by
the crowd), then, after the rounds, fixes on the crowd's WiFi fingerprint map, then encounters between users
found in the call's WiFi scans and Bluetooth sightings, chosen on the filters' estimates and applied as human
anchors (Algorithm 1).

Functions over the tracker's collaborators (engine, detector, selector, fingerprint map, user tracks): the
tracker keeps the order of the stages, these their arithmetic. Pure numerics.
"""

from __future__ import annotations

import math

import numpy as np

from slam_core.background_call import BackgroundCall
from slam_core.crowd.anchor_map import CrowdMapBuilder
from slam_core.crowd.fingerprints import CrowdFingerprints, FingerprintParams, Place, Scan
from slam_core.crowd.graph import CrowdGraph
from slam_core.encounters.detection import DetectionArrays, EncounterDetector, ScanBatch
from slam_core.encounters.selection import EncounterSelector, latest_per_pair, pair_keys
from slam_core.filter.dense_ids import unique_ints, unique_ints_inverse
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.tracking.batches import EncounterResult, EstimateRow, UserBatch, UserReport
from slam_core.tracking.params import TrackerParams
from slam_core.tracking.placement import SlotColumns, TrackTable, carried_since, carry_variance, trail_lookup
from slam_core.tracking.rounds import Round
from slam_core.tracking.trails import UserTrack


def observe_signatures(
    engine: DynamicSlam,
    crowd: CrowdMapBuilder,
    graph: CrowdGraph,
    params: TrackerParams,
    users: dict[str, UserTrack],
    rnd: Round,
    signed: list[int],
    reports: dict[str, UserReport],
    changed: set[int],
) -> None:
    """Signature anchors (beyond the paper): the crowd anchor with that identity, once placed by other
    users, is a position measurement N(anchor; user, anchor cov + signature_sigma^2), gated at
    ``signature_gate_chi2`` against the user's cloud; then the user's pre-update estimate joins the
    anchor. The detection is reported after the closest approach it describes, so the user is placed
    at that moment through its own dead reckoning since (plus 10 % of the distance walked as variance).
    Each user appears at most once per round, so the engine call is one batch."""
    names = [rnd.det_users[k] for k in signed]
    slots = np.array([users[n].slot for n in names], dtype=np.int64)
    before = engine.summaries(slots)
    fix_slots, fix_xy, fix_sigma = [], [], []
    ids = []
    r2 = params.signature_sigma_m**2
    observed = np.array([rnd.det_observed_t[k] for k in signed], dtype=np.int64)
    at_peak, walked_at_peak = trail_lookup(
        TrackTable.of([users[n] for n in names]), np.arange(len(names)), observed
    )
    for name, row, k, then, walked_then in zip(names, before, signed, at_peak, walked_at_peak, strict=True):
        u = users[name]
        shift = u.displacement - then
        drift = float(carry_variance(u.walked - walked_then))
        cov = np.array([[row[2], row[3]], [row[3], row[4]]]) + drift * np.eye(2)
        existing = crowd.find_signature(rnd.det_signature[k])
        if existing is not None and crowd.informed_by_others(existing, u.number):
            anchor_mean, anchor_cov, *_ = crowd.anchor(existing)
            mean = anchor_mean + shift  # where the anchor says the user is now
            variance = float(np.max(np.linalg.eigvalsh(anchor_cov))) + r2 + drift
            d = mean - row[0:2]
            if float(d @ np.linalg.solve(cov + variance * np.eye(2), d)) <= params.signature_gate_chi2:
                fix_slots.append(u.slot)
                u.pin()
                fix_xy.append(mean)
                fix_sigma.append(math.sqrt(variance))
                reports[name].signatures_applied += 1
            else:
                reports[name].signatures_gated += 1
        index = crowd.contribute_signed(
            u.number,
            row[0:2] - shift,
            cov,
            rnd.det_types[k],
            rnd.det_signature[k],
            float(rnd.det_observed_t[k]),
            params.signature_sigma_m,
        )
        ids.append(index)
        if params.crowd_solver == "graph":
            graph.add_detection(u.number, index, then, walked_then, params.signature_sigma_m)
    if fix_slots:
        engine.observe_position(np.array(fix_slots, dtype=np.int64), np.array(fix_xy), np.array(fix_sigma))
    changed.update(ids)


def apply_fingerprint_fixes(
    engine: DynamicSlam,
    fingerprints: CrowdFingerprints,
    params: FingerprintParams,
    located: list[tuple[int, int, np.ndarray, np.ndarray, list[Scan]]],
) -> list[np.ndarray | None]:
    """For each (slot, owner, estimate now, its covariance, the user's scans of this call in time order):
    the latest scan the map can place, carried to now, is a robust fix
    (``DynamicSlam.observe_position_robust``, all of a call's fixes in one engine call), then the confident
    users' scans join the map (``CrowdFingerprints.fix_and_places``). Returns each user's fix, or None."""
    slots, fixes = [], []
    got: list[np.ndarray | None] = []
    places: list[Place] = []
    for slot, owner, xy, cov, scans in located:
        fix, joining = fingerprints.fix_and_places(owner, xy, cov, scans)
        places += joining
        got.append(fix)
        if fix is not None:
            slots.append(slot)
            fixes.append(fix)
    if slots:
        engine.observe_position_robust(
            np.array(slots, dtype=np.int64), np.array(fixes), params.sigma_m, params.outlier_probability,
            params.outlier_radius_m,
        )  # fmt: skip
    for place in places:
        fingerprints.add(place.owner, place.xy, place.bssids, place.rss, place.t_ms)
    return got


def fingerprint_fixes(
    engine: DynamicSlam,
    fingerprints: CrowdFingerprints,
    params: TrackerParams,
    batches: list[UserBatch],
    users: dict[str, UserTrack],
    rows: dict[str, EstimateRow],
    reports: dict[str, UserReport],
) -> None:
    """Each fresh scan of a tracked user, with the user's dead reckoning since it, for
    ``apply_fingerprint_fixes``. ``rows``: the current estimates of the batches' tracked users with scans."""
    stale = params.detection.stale_ap_ms
    names, located = [], []
    scanning = [b for b in batches if b.user in rows]
    if not scanning:
        return
    tracks = [users[b.user] for b in scanning]
    counts = [b.scan_t.size for b in scanning]
    # every scan carried to now at once (``carried_since``: a search per scan had cost ~60 us)
    carried, _, _ = carried_since(
        TrackTable.of(tracks),
        np.repeat(np.arange(len(tracks)), counts),
        np.concatenate([b.scan_t for b in scanning]),
    )
    first = 0
    for b, u in zip(scanning, tracks, strict=True):
        row = rows[b.user]
        scans = []
        for c in range(b.scan_t.size):
            t, bssids, rss = b.fresh_scan(c, stale)
            scans.append(Scan(bssids, rss, carried[first + c], t))
        first += b.scan_t.size
        cov = np.array([[row.cov[0], row.cov[1]], [row.cov[1], row.cov[2]]])
        names.append(b.user)
        located.append((u.slot, u.number, np.array([row.x, row.y]), cov, scans))
    got = apply_fingerprint_fixes(engine, fingerprints, params.fingerprints, located)
    for name, fixed in zip(names, got, strict=True):
        if fixed is not None:
            reports[name].fingerprint_fixes += 1
            reports[name].fingerprint_fix = (float(fixed[0]), float(fixed[1]))


BACKGROUND_SCANS = 16
"""A call with this many scans compares them on a thread of its own while the tracker runs the rounds and
the fingerprint fixes: at 2,000 load-bench phones the comparison was ~9 % of the building's core, and the
kernel releases the GIL. Below it, starting a thread (~0.1 ms) costs more than it hides."""


def start_scan_detection(
    detector: EncounterDetector, batches: list[UserBatch]
) -> BackgroundCall[DetectionArrays]:
    """Hand the call's WiFi scans to the detector (``EncounterDetector.start_scans``): in a busy call they
    are compared on a thread of their own, and nothing else may use the detector until ``encounters`` has
    collected them."""
    scan_users: list[str] = []
    scan_t, scan_offsets, scan_rss, scan_seen = [], [0], [], []
    bssids: list[str] = []
    for b in batches:
        if b.scan_t.size:
            scan_users += [b.user] * b.scan_t.size
            scan_t.append(b.scan_t)
            scan_offsets += (scan_offsets[-1] + b.scan_offsets[1:]).tolist()
            bssids += b.scan_bssid
            scan_rss.append(b.scan_rss)
            scan_seen.append(b.scan_last_seen)
    if not scan_users:
        return BackgroundCall(DetectionArrays.empty, False)
    scans = ScanBatch(
        scan_users,
        np.concatenate(scan_t),
        np.array(scan_offsets, dtype=np.int64),
        bssids,
        np.concatenate(scan_rss),
        np.concatenate(scan_seen),
    )
    return detector.start_scans(scans, background=len(scan_users) >= BACKGROUND_SCANS)


def encounters(
    engine: DynamicSlam,
    detector: EncounterDetector,
    selector: EncounterSelector,
    params: TrackerParams,
    batches: list[UserBatch],
    users: dict[str, UserTrack],
    by_ble: dict[str, str],
    scans: BackgroundCall[DetectionArrays],
    detector_slots: DetectorSlots,
    columns: SlotColumns,
) -> tuple[list[EncounterResult], int]:
    """The encounters chosen among this call's detections (its scans' from ``start_scan_detection``, and
    its Bluetooth sightings'), and how many detections there were. The detections stay arrays until the
    few chosen ones are ranged (a busy building finds thousands)."""
    receivers: list[str] = []
    senders: list[str] = []
    peer_t, peer_rss = [], []
    for b in batches:
        for k in range(b.peer_t.size):
            peer = by_ble.get(b.peer_id[k])
            if peer is not None:
                receivers.append(b.user)
                senders.append(peer)
                peer_t.append(int(b.peer_t[k]))
                peer_rss.append(float(b.peer_rss[k]))
    sightings = (
        detector.add_sightings(receivers, senders, np.array(peer_t), np.array(peer_rss))
        if receivers
        else DetectionArrays.empty()
    )
    found = DetectionArrays.concatenate([scans.result(), sightings])
    slots = detector_slots.of(detector, users, np.concatenate([found.user_a, found.user_b]))  # both at once
    slot_a, slot_b = slots[: len(found)], slots[len(found) :]
    usable = np.flatnonzero((slot_a >= 0) & (slot_b >= 0))
    if usable.size == 0:
        return [], len(found)
    mask, offset, carry_var = _choose(
        engine, detector, selector, users, columns, found.subset(usable), slot_a[usable], slot_b[usable]
    )
    keep = usable[mask]
    chosen = detector.ranged(detector.to_detections(found.subset(keep)))
    if not chosen or not params.filter.use_human_anchors:
        return [EncounterResult(d, False) for d in chosen], len(found)
    outcome = engine.observe_encounters(
        slot_a[keep],
        slot_b[keep],
        np.array([d.distance_m for d in chosen]),
        np.array([d.variance_m2 for d in chosen]) + carry_var,
        offset,
    )
    results = [EncounterResult(d, bool(a)) for d, a in zip(chosen, outcome.applied, strict=True)]
    return results, len(found)


class DetectorSlots:
    """Each detector user id's filter slot (-1: not tracked), kept between calls: a busy call's detections
    name most of the building's users, and looking each one up again every call had cost ~1 ms a group at
    2,000 phones. The tracker calls ``set`` wherever a user's slot changes (a start, a removal); ids the
    detector interned since the last call are looked up when they first appear."""

    def __init__(self) -> None:
        self._table = np.empty(0, dtype=np.int64)

    def of(
        self, detector: EncounterDetector, users: dict[str, UserTrack], user_ids: np.ndarray
    ) -> np.ndarray:
        known = self._table.size
        if detector.n_user_ids > known:
            names = [detector.user_name(i) for i in range(known, detector.n_user_ids)]
            tracks = [users.get(name) for name in names]
            new = [u.slot if u is not None and u.slot >= 0 else -1 for u in tracks]
            self._table = np.concatenate([self._table, np.array(new, dtype=np.int64)])
        result: np.ndarray = self._table[user_ids]
        return result

    def set(self, detector: EncounterDetector, user: str, slot: int) -> None:
        ident = detector.known_user_id(user)
        if ident is not None and ident < self._table.size:
            self._table[ident] = slot


def _choose(
    engine: DynamicSlam,
    detector: EncounterDetector,
    selector: EncounterSelector,
    users: dict[str, UserTrack],
    columns: SlotColumns,
    found: DetectionArrays,
    slot_a: np.ndarray,
    slot_b: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The selector's choice among detections of tracked users (indices into ``found``), from the filters'
    current estimates placed at the detections' times, with each chosen one's offset and carry variance for
    ``DynamicSlam.observe_encounters``.

    Beyond the paper, which applies an encounter as it happens: a batch may span up to a minute and its
    encounters are applied after its steps, so each is carried from its time to now through both users'
    dead reckoning (``slam_core.tracking.trails.carried_since``); one older than either user's trail is left
    out. A peer whose phone has not yet reported up to the reading (its batch comes later: one reading in
    two on the simulated crowd, ~0.5 s behind) is guessed there at its recent velocity, with half the guess
    as its sigma (``SlotColumns.extrapolated``; not at all after 5 s of silence). A busy call has ~12,000
    readings from ~1,100 users: the readings are first narrowed, on the slots' columns, to those the selector
    would consider (each pair's latest) and could choose (within its range of each other once either user's
    walk since, or its guessed walk beyond its last report, is allowed for), and only the users of those who
    walked after them are carried back step by step."""
    n = len(found)
    slots, index = unique_ints_inverse(np.concatenate([slot_a, slot_b]))
    means = engine.means(slots)
    delta_now = means[index[:n]] - means[index[n:]]
    keys = pair_keys(found.user_a, found.user_b, found.model)
    latest = latest_per_pair(found.t_ms, keys)
    t = found.t_ms[latest]
    sa, sb = slot_a[latest], slot_b[latest]
    ahead_a, guess_a, heard_a = columns.extrapolated(sa, t)
    ahead_b, guess_b, heard_b = columns.extrapolated(sb, t)
    bound = np.hypot(delta_now[latest, 0], delta_now[latest, 1])
    bound -= columns.reach(sa, t) + np.hypot(ahead_a[:, 0], ahead_a[:, 1])
    bound -= columns.reach(sb, t) + np.hypot(ahead_b[:, 0], ahead_b[:, 1])
    # a reading can be chosen only where its model's range sigma passes the selector's gate: for WiFi that is
    # ~2.3 m, well inside the selection range (~5x fewer readings carried back at 2,000 phones)
    limit = np.full(int(found.model.max()) + 1, selector.params.select_range_m)
    for model in unique_ints(found.model[latest]):
        limit[model] = detector.range_model(int(model)).sigma_reach(
            selector.params.max_sigma_m, selector.params.select_range_m
        )
    near = np.flatnonzero((bound <= limit[found.model[latest]]) & heard_a & heard_b)
    c = near.size
    # only users who reported steps after a reading are carried back, their tracks looked up by name
    t2 = np.concatenate([t[near], t[near]])
    rows = np.flatnonzero(columns.last_t_ms[np.concatenate([sa[near], sb[near]])] > t2)
    ids, who = unique_ints_inverse(
        np.concatenate([found.user_a[latest[near]], found.user_b[latest[near]]])[rows]
    )
    shift, walked, placeable = np.zeros((2 * c, 2)), np.zeros(2 * c), np.ones(2 * c, dtype=bool)
    if rows.size:
        table = TrackTable.of([users[detector.user_name(i)] for i in ids.tolist()])
        shift[rows], walked[rows], placeable[rows] = carried_since(table, who, t2[rows])
    ok = np.flatnonzero(placeable[:c] & placeable[c:])
    candidates = latest[near[ok]]
    # a user's position then is where it is now minus its walk since, or plus its guessed walk beyond
    offset = (shift[:c] - shift[c:])[ok] - (ahead_a - ahead_b)[near[ok]]
    carry_var = (carry_variance(walked[:c]) + carry_variance(walked[c:]))[ok]
    carry_var += (guess_a + guess_b)[near[ok]]
    delta = delta_now[candidates] - offset
    predicted = np.hypot(delta[:, 0], delta[:, 1])
    sigma = np.empty(candidates.size)
    models = found.model[candidates]
    for model in unique_ints(models):
        at = models == model
        sigma[at] = np.sqrt(detector.range_model(int(model)).variance_at_distance(predicted[at]))
    chosen = selector.choose(found.t_ms[candidates], keys[candidates], predicted, sigma)
    if len(selector) > 100_000:
        selector.forget_before(int(found.t_ms.max()))
    return candidates[chosen], offset[chosen], carry_var[chosen]
