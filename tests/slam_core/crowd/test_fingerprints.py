"""The crowd-learned fingerprint map (weighted kNN against a direct computation over wifi_pairs' union
distance) and the engine's robust position fix it feeds."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from slam_core.crowd.fingerprint_index import knn_position
from slam_core.crowd.fingerprints import (
    STALE_BOUND,
    SURVEY_OWNER,
    CrowdFingerprints,
    FingerprintParams,
    Scan,
)
from slam_core.filter.dynamic_slam import DynamicSlam
from slam_core.filter.params import FilterParams
from slam_core.signalslam.maps import FingerprintGrid, localise_knn
from slam_core.wifi.pairs import fingerprint_matrix


def _scans(rng: np.random.Generator, n: int, aps: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Scans at random places of a 60 m x 30 m floor, log-distance RSS from APs on a grid; NaN below -90."""
    xy = rng.uniform([0, 0], [60, 30], size=(n, 2))
    ap = np.column_stack([np.tile(np.linspace(5, 55, aps // 2), 2), np.repeat([8.0, 22.0], aps // 2)])
    d = np.linalg.norm(xy[:, None, :] - ap[None, :, :], axis=2)
    rss = -40.0 - 25.0 * np.log10(np.maximum(d, 1.0)) + rng.normal(0, 2.0, d.shape)
    return xy, np.where(rss > -90.0, rss, np.nan)


MINUTE_MS = 60_000
"""Scans a minute apart: a full cell always takes the next (``cell_refresh_ms`` is 30 s)."""


def _add_all(db: CrowdFingerprints, owners: np.ndarray, xy: np.ndarray, rss: np.ndarray) -> list[str]:
    names = [f"ap{i}" for i in range(rss.shape[1])]
    for i, (o, p, row) in enumerate(zip(owners, xy, rss, strict=True)):
        heard = np.isfinite(row)
        assert db.add(
            int(o), p, [n for n, h in zip(names, heard, strict=True) if h], row[heard], i * MINUTE_MS
        )
    return names


def test_locate_is_weighted_knn_over_the_union_distance() -> None:
    rng = np.random.default_rng(3)
    xy, rss = _scans(rng, 300)
    db = CrowdFingerprints(FingerprintParams(max_spread_m=1e9, per_cell=300))  # the oracle keeps every scan
    names = _add_all(db, np.arange(300) % 5 + 1, xy, rss)
    q_xy, q_rss = _scans(rng, 20)
    oracle = localise_knn(FingerprintGrid(xy, rss, np.isfinite(rss), np.ones(300)), q_rss, k=7)
    for row, expected in zip(q_rss, oracle, strict=True):
        heard = np.isfinite(row)
        found = db.locate(0, [n for n, h in zip(names, heard, strict=True) if h], row[heard])
        assert found is not None
        np.testing.assert_allclose(found, expected, atol=1e-3)
    errors = np.linalg.norm(oracle - q_xy, axis=1)
    assert np.median(errors) < 5.0  # and the map is useful on a clean floor


def test_own_scans_are_never_references_and_small_maps_say_nothing() -> None:
    rng = np.random.default_rng(4)
    xy, rss = _scans(rng, 60)
    db = CrowdFingerprints(FingerprintParams(min_references=50, max_spread_m=1e9))
    names = _add_all(db, np.zeros(60, dtype=np.int64), xy, rss)
    heard = np.isfinite(rss[0])
    query = ([n for n, h in zip(names, heard, strict=True) if h], rss[0][heard])
    assert db.locate(0, *query) is None  # every reference is the user's own
    assert db.locate(1, *query) is not None
    assert db.locate(1, query[0][:2], query[1][:2]) is None  # fewer than min_aps
    assert db.locate(1, ["never-seen"] * 5, np.full(5, -60.0)) is None  # no AP in common


def test_the_map_is_a_bounded_ring() -> None:
    rng = np.random.default_rng(5)
    xy, rss = _scans(rng, 300)
    db = CrowdFingerprints(FingerprintParams(k=3, min_references=10, max_references=100))
    _add_all(db, np.ones(300, dtype=np.int64), xy, rss)
    assert len(db) == 100
    assert db._xy.shape[0] == 100


def _brute_force_knn(
    refs: list[tuple[int, np.ndarray, np.ndarray]], owner: int, query: np.ndarray, k: int
) -> np.ndarray | None:
    """Weighted kNN over ``wifi_pairs.fingerprint_matrix`` of dense rows (NaN: not heard), others' only."""
    rss = np.vstack([r[2] for r in refs] + [query])
    d = fingerprint_matrix(rss)[-1, :-1]
    heard = np.isfinite(rss)
    usable = np.array([o != owner for o, _, _ in refs]) & (heard[:-1] & heard[-1]).any(axis=1)
    d = np.where(usable, d, np.inf)
    nearest = np.argsort(d, kind="stable")[:k]
    if not np.all(np.isfinite(d[nearest])):
        return None
    w = 1.0 / np.maximum(d[nearest], 1e-3)
    return (w / w.sum()) @ np.array([refs[i][1] for i in nearest])


@pytest.mark.parametrize(("cell_m", "per_cell"), [(4.0, 16), (10.0, 3)])
def test_the_inverted_index_matches_brute_force_through_evictions_and_compactions(
    cell_m: float, per_cell: int
) -> None:
    """Many APs, few heard per scan, a small map that turns over five times, by age (large cells) or by
    place (small cells): every query equals weighted kNN over the union distance of the scans the map should
    hold (the newest per_cell of each cell, and the newest max_references of all), and the pool of postings
    stays proportional to the live ones."""
    rng = np.random.default_rng(11)
    n_aps, ring = 400, 120
    params = FingerprintParams(
        k=5, min_references=20, max_references=ring, max_spread_m=1e9, cell_m=cell_m, per_cell=per_cell
    )
    db = CrowdFingerprints(params)
    names = [f"ap{i}" for i in range(n_aps)]
    kept: list[tuple[int, np.ndarray, np.ndarray]] = []
    checked = 0
    for t in range(6 * ring):
        row = np.full(n_aps, np.nan)
        area = rng.integers(0, n_aps - 30)  # scans hear a window of nearby APs: neighbours share postings
        heard = area + rng.choice(30, size=rng.integers(3, 15), replace=False)
        row[heard] = rng.integers(-99 * 64, -40 * 64, heard.size) / 64.0  # exact in float32, rarely tied
        xy, owner = rng.uniform(0, 50, 2), int(rng.integers(0, 6))
        if t % 3 == 0 and len(kept) >= params.min_references:
            expected = _brute_force_knn(kept, owner, row, params.k)
            found = db.locate(owner, [names[i] for i in heard], row[heard])
            assert (found is None) == (expected is None)
            if found is not None:
                np.testing.assert_allclose(found, expected, atol=1e-9)
                checked += 1
        assert db.add(owner, xy, [names[i] for i in heard], row[heard], t * MINUTE_MS)
        same_cell = [i for i, r in enumerate(kept) if np.array_equal(r[1] // cell_m, xy // cell_m)]
        if len(same_cell) >= per_cell:
            del kept[same_cell[0]]
        elif len(kept) >= ring:
            del kept[0]
        kept.append((owner, xy, row))
        assert len(db) == len(kept)
        live = sum(int(np.isfinite(r).sum()) for _, _, r in kept)
        assert db.postings <= 3 * live + 4 * n_aps
        assert 0 <= db.stale_postings <= (STALE_BOUND - 1) * live + 4
        stale = sum(
            int(db._serial[db._post_row[p]] != db._post_serial[p])
            for c in range(len(db._columns))
            for p in range(db._start[c], db._start[c] + db._length[c])
        )
        assert stale == db.stale_postings
    assert checked > 100
    assert pickle.loads(pickle.dumps(db)).stale_postings == db.stale_postings


def test_a_full_cell_takes_a_scan_only_once_its_newest_is_cell_refresh_ms_old() -> None:
    """A cell fills freely; full, it refuses scans until its newest is ``cell_refresh_ms`` old, then the new
    scan replaces its oldest. Other cells are not held back, and a refusal changes nothing."""
    params = FingerprintParams(k=1, min_references=1, per_cell=2, cell_refresh_ms=10_000, max_spread_m=1e9)
    db = CrowdFingerprints(params)
    aps = ["a", "b", "c"]

    def add(x: float, t_ms: int, rss: float) -> bool:
        return db.add(1, np.array([x, 1.0]), aps, np.full(3, rss), t_ms)

    assert add(1.0, 0, -50.0)  # the cell [0, 4) fills
    assert add(2.0, 1_000, -60.0)
    before = (len(db), db.postings, db._xy.copy())
    assert not add(3.0, 10_999, -70.0)  # full, and its newest is 9.999 s old
    assert (len(db), db.postings) == before[:2]
    np.testing.assert_array_equal(db._xy, before[2])
    assert add(5.0, 5_000, -70.0)  # another cell
    assert add(3.0, 11_000, -80.0)  # 10 s after the newest: replaces the oldest (x = 1, -50 dBm)
    assert len(db) == 3
    at = db.locate(2, aps, np.full(3, -50.0))
    assert at is not None
    assert at[0] == 2.0  # the -50 dBm scan is gone: the nearest is now the -60 dBm one
    assert not add(3.0, 1_001, -50.0)  # 9.999 s before the newest is as near in time
    assert add(3.0, 3_600_000 + 11_000, -90.0)  # a clock an hour ahead replaces the oldest (x = 2)...
    assert add(3.5, 12_000, -55.0)  # ...and holds the cell for nobody: the others' next scan still lands
    assert len(db) == 3
    at = db.locate(2, aps, np.full(3, -50.0))
    assert at is not None
    assert at[0] == 3.5
    unlimited = CrowdFingerprints(FingerprintParams(per_cell=1, cell_refresh_ms=0))
    assert all(unlimited.add(1, np.array([1.0, 1.0]), aps, np.full(3, -50.0), 0) for _ in range(3))


def test_a_builds_scans_keep_their_cell_and_are_every_users() -> None:
    """Scans of a signal-map build (``SURVEY_OWNER``) are located on by every user; a user's scan takes a
    full cell's oldest user scan, never a build's, and a cell full of a build's scans takes none."""
    params = FingerprintParams(k=1, min_references=1, per_cell=2, cell_refresh_ms=0, max_spread_m=1e9)
    db = CrowdFingerprints(params)
    aps = ["a", "b", "c"]
    assert db.add(SURVEY_OWNER, np.array([1.0, 1.0]), aps, np.full(3, -50.0), 0)
    assert db.add(7, np.array([2.0, 1.0]), aps, np.full(3, -60.0), 1)
    assert db.add(8, np.array([3.0, 1.0]), aps, np.full(3, -70.0), 2)  # full: user 7's scan leaves
    assert db._per_owner == {SURVEY_OWNER: 1, 8: 1}
    located = db.locate(8, aps, np.full(3, -52.0))  # user 8 is located on the build's scan
    assert located is not None
    assert located[0] == 1.0
    assert db.add(SURVEY_OWNER, np.array([5.0, 1.0]), aps, np.full(3, -50.0), 3)
    assert db.add(SURVEY_OWNER, np.array([6.0, 1.0]), aps, np.full(3, -50.0), 4)
    assert not db.add(9, np.array([7.0, 1.0]), aps, np.full(3, -50.0), 5)  # the build holds that cell
    assert db._per_owner == {SURVEY_OWNER: 3, 8: 1}


def test_fingerprint_params_are_checked() -> None:
    for bad, message in (
        ({"k": 0}, "k <="),
        ({"min_references": 3, "k": 7}, "k <= min_references"),
        ({"max_references": 10}, "min_references <= max_references"),
        ({"sigma_m": 0.0}, "positive"),
        ({"outlier_probability": 1.0}, "outlier_probability"),
        ({"min_aps": 0}, "min_aps"),
        ({"cell_m": 0.0}, "cell_m"),
        ({"per_cell": 0}, "per_cell"),
        ({"cell_refresh_ms": -1}, "cell_refresh_ms"),
    ):
        with pytest.raises(ValueError, match=message):
            FingerprintParams(**bad)  # type: ignore[arg-type]


def _spread_user(engine: DynamicSlam) -> int:
    return engine.add_user(0.0, 0.0, position_sigma=3.0)


def test_a_near_fix_concentrates_the_cloud_and_a_far_one_barely_moves_it() -> None:
    params = FilterParams(n_particles=200)
    near, far = DynamicSlam(params, seed=1), DynamicSlam(params, seed=1)
    for engine in (near, far):
        _spread_user(engine)
    before = near.summaries(np.array([0]))[0]
    near.observe_position_robust(np.array([0]), np.array([[2.0, 0.0]]), 1.5, 0.3, 50.0)
    far.observe_position_robust(np.array([0]), np.array([[40.0, 0.0]]), 1.5, 0.3, 50.0)
    for engine in (near, far):
        w = np.exp(engine.state.logw[0])
        np.testing.assert_allclose(w.sum(), 1.0, atol=1e-9)
        assert np.all(np.isfinite(engine.summaries(np.array([0]))))
    after_near, after_far = near.summaries(np.array([0]))[0], far.summaries(np.array([0]))[0]
    assert after_near[0] > before[0] + 1.0  # pulled toward the fix at x = 2
    assert after_near[2] < 0.7 * before[2]  # and narrower
    assert abs(after_far[0] - before[0]) < 1.0  # the outlier term: a fix 40 m away is not believed


def test_robust_fix_rejects_bad_input_and_changes_nothing() -> None:
    engine = DynamicSlam(FilterParams(n_particles=20), seed=0)
    _spread_user(engine)
    before = {k: v.copy() for k, v in vars(engine.state).items()}
    for call, message in (
        (
            lambda: engine.observe_position_robust(np.array([0]), np.array([[np.nan, 0.0]]), 5, 0.3, 50),
            "finite",
        ),
        (
            lambda: engine.observe_position_robust(np.array([0]), np.zeros((2, 2)), 5.0, 0.3, 50.0),
            "one finite",
        ),
        (lambda: engine.observe_position_robust(np.array([0]), np.zeros((1, 2)), 0.0, 0.3, 50.0), "positive"),
        (
            lambda: engine.observe_position_robust(np.array([0]), np.zeros((1, 2)), 5.0, 1.0, 50.0),
            "outlier_probability",
        ),
    ):
        with pytest.raises(ValueError, match=message):
            call()
    for k, v in vars(engine.state).items():
        np.testing.assert_array_equal(v, before[k], err_msg=k)


def test_fix_and_places_carries_the_latest_fix_and_keeps_only_confident_scans() -> None:
    rng = np.random.default_rng(6)
    xy, rss = _scans(rng, 120)
    db = CrowdFingerprints(FingerprintParams(max_spread_m=1e9, per_cell=300))
    names = _add_all(db, np.ones(120, dtype=np.int64), xy, rss)
    _, q_rss = _scans(rng, 2)
    scans = []
    for row, shift in zip(q_rss, ([3.0, 0.0], [1.0, -1.0]), strict=True):
        heard = np.isfinite(row)
        heard_names = [n for n, h in zip(names, heard, strict=True) if h]
        scans.append(Scan(heard_names, row[heard], np.array(shift), 200 * MINUTE_MS + len(scans)))
    latest = db.locate(2, scans[1].bssids, scans[1].rss)
    assert latest is not None
    here = np.array([10.0, 10.0])
    (fix, places), (none, _) = db.fixes_and_places(
        [(2, here, np.diag([4.0, 1.0]), scans), (1, here, np.diag([4.0, 1.0]), scans)]
    )
    assert none is None  # every reference is user 1's own
    assert fix is not None
    np.testing.assert_allclose(fix, latest + np.array([1.0, -1.0]))  # the latest scan, carried to now
    assert [p.owner for p in places] == [2, 2]
    np.testing.assert_allclose([p.xy for p in places], [here - [3.0, 0.0], here - [1.0, -1.0]])
    assert [p.t_ms for p in places] == [s.t_ms for s in scans]
    # an estimate whose larger axis' sigma exceeds max_reference_std_m (3 m) adds nothing to the map
    tilted = np.array([[5.0, 4.5], [4.5, 5.0]])  # eigenvalues 0.5 and 9.5
    assert db.fixes_and_places([(2, here, tilted, scans)])[0][1] == []
    assert db.fixes_and_places([(2, here, np.diag([9.0, 9.0]), scans)])[0][1] != []


def test_many_scans_located_in_one_call_are_each_located_alone() -> None:
    """``locate_many`` against its oracle: each scan's k nearest by ``_neighbours`` (one search each) and
    their weighted kNN position, None where those say the map cannot place it (a user's own scans, too few
    APs, neighbours spread too far)."""
    rng = np.random.default_rng(11)
    xy, rss = _scans(rng, 200)
    db = CrowdFingerprints(FingerprintParams(max_spread_m=6.0, per_cell=300))
    names = _add_all(db, rng.integers(1, 4, 200), xy, rss)
    queries = []
    for owner, row in zip(rng.integers(0, 5, 60).tolist(), _scans(rng, 60)[1], strict=True):
        heard = np.isfinite(row)
        queries.append((owner, [n for n, h in zip(names, heard, strict=True) if h], row[heard]))
    queries.append((0, queries[0][1][:2], queries[0][2][:2]))  # fewer than min_aps
    got = db.locate_many(queries)
    placed = 0
    for (owner, bssids, q_rss), found in zip(queries, got, strict=True):
        near = db._neighbours(owner, bssids, q_rss)
        expected = None
        if near is not None:
            x, y, spread = knn_position(db._xy, *near)
            expected = None if spread > 6.0 else np.array([x, y])
        if expected is None:
            assert found is None
        else:
            placed += 1
            assert found is not None
            np.testing.assert_allclose(found, expected, rtol=0, atol=1e-12)
    assert 10 < placed < len(queries) - 1  # both answers are exercised


def test_bssids_no_stored_scan_hears_are_forgotten() -> None:
    """Every scan hears three fixed APs and a hotspot never seen again: after many turnovers of a small map
    the column index holds the fixed APs and the hotspots of the scans still stored, not every hotspot ever
    heard, and the map answers as a fresh one holding the same scans does."""
    rng = np.random.default_rng(8)
    params = FingerprintParams(k=3, min_references=10, max_references=40, max_spread_m=1e9)
    db = CrowdFingerprints(params)
    scans = []
    for t in range(2_000):
        scan = (t % 5, rng.uniform(0, 50, 2), ["fixed-a", "fixed-b", "fixed-c", f"hotspot-{t}"])
        scans.append((*scan, rng.uniform(-90.0, -50.0, 4), t * MINUTE_MS))
        db.add(*scans[-1])
    assert len(db) == 40
    assert len(db._columns) <= 3 + 3 * 40  # fixed APs, and hotspots of stored scans and a little slack
    fresh = CrowdFingerprints(params)
    for scan in scans[-40:]:
        fresh.add(*scan)
    for query in (["fixed-a", "fixed-b", "fixed-c"], ["fixed-a", "fixed-c", "hotspot-1999"]):
        rss = rng.uniform(-90.0, -50.0, 3)
        found, expected = db.locate(99, query, rss), fresh.locate(99, query, rss)
        assert found is not None
        assert expected is not None
        np.testing.assert_allclose(found, expected, atol=1e-9)
