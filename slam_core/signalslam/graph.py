"""GraphSLAM and SignalSLAM over many walks at once, on gtsam (SignalSLAM Sections II-C to II-E).

Each walk is a chain of ``Pose2`` vertices, one per PDR step between its first and last landmark. Edges:

- **motion** (Eq. 5 terms): ``BetweenFactorPose2`` from each step (length, change of heading);
- **landmark**: ``PoseTranslationPrior2D`` at a landmark with a known position (position only: the paper's
  omega_33 = 0; gtsam's factor is exact for it, where a ``BetweenFactorPose2`` with zero heading information
  mis-weights the translation);
- **signal** (Eq. 7): for each 10 s signal window, the kernel-weighted mean of the current positions of its
  ``n`` most similar windows on other walks is a temporary absolute landmark, re-evaluated after every
  optimisation while the neighbour sets stay fixed; these edges get a Huber kernel because a fraction of
  signal neighbours are far away (wrong similarity).

Departures from the paper, said here: the paper sets every information matrix to identity (omega_33 = 4) on
stride edges; our vertices are single steps, so the motion noise is per step (``SignalGraphParams``), and the
signal-edge sigma is the regression's measured accuracy (metres, not the paper's unit information), widened
for the overlap of the 10 s windows. Beyond the paper, each walk's start pose has a prior on its heading (the
phone's heading, with the heading-bias sigma): with landmarks at both ends a straight walk is held by them,
but a walk that comes back near its start could otherwise turn freely about them (on msindoor site1 F1,
GraphSLAM p90 6.3 m without the prior, 3.5 m with it). Optimisation is Levenberg-Marquardt from the
recalibrated dead reckoning (Eq. 4, in its posterior form: ``calibration.CalibrationPrior``).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from slam_core.signalslam.calibration import CalibrationGrid, CalibrationPrior, calibrate_segment, dead_reckon
from slam_core.signalslam.similarity import (
    gaussian_kernel,
    kl_kernel,
    union_gaussian_kernel,
    visibility_multinomials,
)
from slam_core.signalslam.windows import WINDOW_MS, WINDOW_STEP_MS

MODALITIES = ("wifi", "bluetooth", "magnetic", "lte")
SOLVERS = ("lm", "isam2")


@dataclass(frozen=True)
class SignalGraphParams:
    step_sigma_along_m: float = 0.20
    """Per step, what a walk's scale does not explain: between consecutive waypoints of msindoor site1 F1,
    after each walk's own scale, segment lengths scatter by 0.10 in log ratio over ~12 steps, about 0.25 m
    per step (an upper bound: the surveyed line between clicks has its own error)."""
    step_sigma_across_m: float = 0.05
    step_sigma_heading_rad: float = np.radians(1.0)
    """Per step: the phone's heading error is mostly a constant bias per walk, which the start pose's heading
    absorbs (within ``start_heading_prior``); what varies step to step is about a degree."""
    landmark_sigma_m: float = 0.5
    signal_sigma_m: float = 5.0
    """A WiFi kernel regression is good to about 5 m on a mall floor (Eq. 7 on surveyed neighbour positions:
    4.5 m p50 on msindoor site1 F1), so one window's signal edge is a 5 m landmark, made robust by the Huber
    kernel; ``signal_overlap`` widens it for the windows that share its scans."""
    signal_overlap: float = WINDOW_MS / WINDOW_STEP_MS
    """Windows of 10 s every 1 s: each scan is in 10 windows, so their edges are not independent
    observations. Each edge's sigma is ``signal_sigma_m * sqrt(signal_overlap)`` so that one 10 s stretch of
    scans carries one landmark's information, not ten."""
    signal_huber_k: float = 1.345
    neighbours: int = 10  # n of Eq. 7
    kernel_alpha: float = 1.0
    magnetic_alpha: float = 1.0 / (2 * 4.0**2)
    """Gaussian kernel on the windows' mean magnetic magnitude: a 4 uT difference is one sigma (the
    magnitude wanders by tens of uT across a mall floor, a few uT between passes of one place)."""
    lte_alpha: float = 1.0 / (2 * 6.0**2)
    """Gaussian kernel on the windows' LTE RSRP over their union of cells: 6 dB is one sigma (indoor
    shadowing of a cell's RSRP)."""
    lte_floor_dbm: float = -120.0
    """A cell one window did not hear counts at this RSRP (about where phones lose an LTE cell)."""
    solver: str = "lm"
    """``lm``: batch Levenberg-Marquardt from the recalibrated dead reckoning; ``isam2``: the poses fed to
    iSAM2 in chunks of ``chunk_poses`` (the robust choice on long walks, where batch optimisation from
    dead reckoning stops in poor minima), signal edges swapped in place at each re-evaluation."""
    chunk_poses: int = 30
    modalities: tuple[str, ...] = ("wifi",)
    """Kernels multiplied into the signal similarity. On msindoor site1 F1 (``crowdslam signalslam``):
    WiFi alone 1.40 / 2.91 m (p50 / p90), + fixed Bluetooth beacons 1.52 / 3.26, + magnetic magnitude
    1.42 / 2.93, all three 1.56 / 3.39: the beacons' sparse, noisy visibility and the magnetic magnitude's
    ambiguity over a large floor reorder WiFi's good neighbours, so WiFi alone is the default."""

    same_walk_gap_ms: int = 20_000
    """Windows of the same walk closer in time than this are not signal neighbours (they overlap)."""
    iterations: int = 5
    calibration_prior: bool = True
    """Beyond the paper: recalibrate (Eq. 4) on the posterior with the bias-scale priors
    (``CalibrationPrior``); False is the paper's plain grid search."""
    start_heading_prior: bool = True
    """Beyond the paper: a prior on each walk's start heading, the phone's heading with the heading-bias
    sigma. Without it a walk that ends near its start may turn freely about its landmarks (the motion
    edges are relative and the landmarks position-only)."""

    def __post_init__(self) -> None:
        if self.solver not in SOLVERS or self.chunk_poses < 1:
            raise ValueError(f"solver must be one of {', '.join(SOLVERS)} and chunk_poses >= 1")
        unknown = [m for m in self.modalities if m not in MODALITIES]
        if unknown or not self.modalities:
            raise ValueError(f"unknown modalities {unknown}; valid: {', '.join(MODALITIES)}")
        if min(self.step_sigma_along_m, self.step_sigma_across_m, self.step_sigma_heading_rad,
               self.landmark_sigma_m, self.signal_sigma_m) <= 0 or self.signal_overlap < 1:  # fmt: skip
            raise ValueError("graph sigmas must be positive and signal_overlap >= 1")


@dataclass(frozen=True)
class Walk:
    """One walk's dead reckoning between its landmarks, and its signal windows."""

    t_ms: np.ndarray  # (N + 1,) the start landmark's time, then each step's
    lengths: np.ndarray  # (N,)
    headings: np.ndarray  # (N,) rad, counter-clockwise from east
    start: np.ndarray  # (2,) the first landmark
    end: np.ndarray  # (2,) the last landmark (reached at t_ms[-1])
    window_t: np.ndarray  # (W,) signal window centres
    window_counts: np.ndarray  # (W, A) AP sightings per window (global AP columns)
    window_beacons: np.ndarray | None = None  # (W, B) Bluetooth beacon sightings per window
    window_magnetic: np.ndarray | None = None  # (W,) mean magnetic magnitude (uT), NaN without samples
    window_lte: np.ndarray | None = None  # (W, C) mean LTE RSRP per cell (dBm), NaN where not heard


@dataclass(frozen=True)
class Trajectories:
    raw: list[np.ndarray]  # per walk (N + 1, 2)
    calibrated: list[np.ndarray]
    graphslam: list[np.ndarray]
    signalslam: list[np.ndarray]


def _key(index: int) -> int:
    return int(gtsam.symbol("x", index))


def _relative(h0: float, h1: float, length: float) -> gtsam.Pose2:
    """Step of ``length`` along ``h1`` seen from a pose heading ``h0``, ending heading ``h1``."""
    turn = h1 - h0
    return gtsam.Pose2(length * np.cos(turn), length * np.sin(turn), turn)


class WalkGraph:
    """The joint graph of all walks: motion and landmark edges; signal edges added per iteration."""

    def __init__(self, walks: list[Walk], params: SignalGraphParams) -> None:
        self.walks = walks
        self.params = params
        self.offsets = np.concatenate([[0], np.cumsum([w.lengths.size + 1 for w in walks])]).astype(int)
        self.base = gtsam.NonlinearFactorGraph()
        self.newest_pose: list[int] = []  # per factor of ``base``: the highest pose index it touches
        p = params
        motion = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([p.step_sigma_along_m, p.step_sigma_across_m, p.step_sigma_heading_rad])
        )
        landmark = gtsam.noiseModel.Isotropic.Sigma(2, p.landmark_sigma_m)
        heading_prior = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([1e3, 1e3, CalibrationPrior().offset_sigma_rad])
        )
        for w, walk in enumerate(walks):
            o = self.offsets[w]
            heads = np.concatenate([[walk.headings[0]], walk.headings])  # the start pose faces the first step
            for k in range(walk.lengths.size):
                rel = _relative(heads[k], heads[k + 1], float(walk.lengths[k]))
                self.base.add(gtsam.BetweenFactorPose2(_key(o + k), _key(o + k + 1), rel, motion))
                self.newest_pose.append(o + k + 1)
            self.base.add(
                gtsam.PoseTranslationPrior2D(_key(o), np.asarray(walk.start, dtype=float), landmark)
            )
            self.newest_pose.append(o)
            if p.start_heading_prior:
                start = gtsam.Pose2(float(walk.start[0]), float(walk.start[1]), float(heads[0]))
                self.base.add(gtsam.PriorFactorPose2(_key(o), start, heading_prior))
                self.newest_pose.append(o)
            last = o + walk.lengths.size
            self.base.add(
                gtsam.PoseTranslationPrior2D(_key(last), np.asarray(walk.end, dtype=float), landmark)
            )
            self.newest_pose.append(last)

    def values(self, positions: list[np.ndarray]) -> gtsam.Values:
        values = gtsam.Values()
        for w, (walk, xy) in enumerate(zip(self.walks, positions, strict=True)):
            heads = np.concatenate([[walk.headings[0]], walk.headings])
            for k in range(xy.shape[0]):
                values.insert(
                    _key(self.offsets[w] + k), gtsam.Pose2(float(xy[k, 0]), float(xy[k, 1]), heads[k])
                )
        return values

    def positions(self, values: gtsam.Values) -> list[np.ndarray]:
        out = []
        for w, walk in enumerate(self.walks):
            o = self.offsets[w]
            out.append(
                np.array([[values.atPose2(_key(o + k)).x(), values.atPose2(_key(o + k)).y()]
                          for k in range(walk.lengths.size + 1)])
            )  # fmt: skip
        return out

    def optimise(self, graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values) -> gtsam.Values:
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        return gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()


class _Incremental:
    """iSAM2 fed the graph's poses in chunks (walk by walk, ``chunk_poses`` at a time), then signal edges
    replaced in place (``removeFactorIndices``) at each re-evaluation."""

    def __init__(self, graph: WalkGraph, initial: gtsam.Values, chunk: int) -> None:
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(0.01)  # metres / radians: steps are ~0.7 m, 0.1 leaves drift
        isam_params.relinearizeSkip = 1
        self.isam = gtsam.ISAM2(isam_params)
        # A chain with a position-only landmark at its start turns freely about it until its end landmark
        # arrives in a later chunk: a loose prior on each start pose (1 rad on heading) fixes that gauge.
        loose = gtsam.noiseModel.Diagonal.Sigmas(np.array([100.0, 100.0, 1.0]))
        starts = {int(o): gtsam.PriorFactorPose2(_key(int(o)), initial.atPose2(_key(int(o))), loose)
                  for o in graph.offsets[:-1]}  # fmt: skip
        order = np.argsort(graph.newest_pose, kind="stable")
        newest = np.asarray(graph.newest_pose)[order]
        n_poses = int(graph.offsets[-1])
        start = 0
        for lo in range(0, n_poses, chunk):
            hi = min(lo + chunk, n_poses)
            end = int(np.searchsorted(newest, hi, side="left"))
            factors = gtsam.NonlinearFactorGraph()
            for i in order[start:end]:
                factors.add(graph.base.at(int(i)))
            for k in range(lo, hi):
                if k in starts:
                    factors.add(starts[k])
            values = gtsam.Values()
            for k in range(lo, hi):
                values.insert(_key(k), initial.atPose2(_key(k)))
            self.isam.update(factors, values)
            start = end
        for _ in range(3):  # relinearise what the last chunks moved
            self.isam.update()
        self._signal: list[int] = []

    def estimate(self) -> gtsam.Values:
        return self.isam.calculateEstimate()

    def replace_signal_edges(self, edges: gtsam.NonlinearFactorGraph, relinearise: int = 3) -> gtsam.Values:
        result = self.isam.update(edges, gtsam.Values(), self._signal)
        self._signal = list(result.getNewFactorsIndices())
        for _ in range(relinearise):
            self.isam.update()
        return self.isam.calculateEstimate()


def calibrated_positions(
    walks: list[Walk], grid: CalibrationGrid | None = None, prior: CalibrationPrior | None = None
) -> list[np.ndarray]:
    """Eq. 4 per walk (its landmarks at both ends), with ``prior`` its posterior form, applied to the
    whole walk."""
    grid = grid or CalibrationGrid()
    out = []
    for walk in walks:
        scale, offset, _ = calibrate_segment(walk.lengths, walk.headings, walk.start, walk.end, grid, prior)
        out.append(
            np.vstack([walk.start, dead_reckon(walk.lengths, walk.headings, walk.start, scale, offset)])
        )
    return out


def signal_neighbours(
    walks: list[Walk], params: SignalGraphParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every window: its walk, the indices of its ``n`` most similar windows on other walks (or far in
    time on its own), and their kernel values. Kernels (Section II-D): KL on WiFi AP visibility, KL on
    Bluetooth beacon visibility, Gaussian on magnetic magnitude, Gaussian on LTE RSRP over the union of
    cells, multiplied element-wise; a modality a window lacks is neutral (1) for its pairs."""
    walk_of = np.concatenate([np.full(w.window_t.size, i) for i, w in enumerate(walks)])
    times = np.concatenate([w.window_t for w in walks])
    kernel = np.ones((times.size, times.size))
    if "wifi" in params.modalities:
        kernel *= _visibility_kernel(np.vstack([w.window_counts for w in walks]), params.kernel_alpha)
    if "bluetooth" in params.modalities and all(w.window_beacons is not None for w in walks):
        beacons = np.vstack([w.window_beacons for w in walks if w.window_beacons is not None])
        kernel *= _visibility_kernel(beacons, params.kernel_alpha)
    if "magnetic" in params.modalities and all(w.window_magnetic is not None for w in walks):
        magnitude = np.concatenate([w.window_magnetic for w in walks if w.window_magnetic is not None])
        has = np.isfinite(magnitude)
        block = gaussian_kernel(np.where(has, magnitude, 0.0), alpha=params.magnetic_alpha)
        kernel *= np.where(has[:, None] & has[None, :], block, 1.0)
    if "lte" in params.modalities and all(w.window_lte is not None for w in walks):
        rsrp = np.vstack([w.window_lte for w in walks if w.window_lte is not None])
        has = np.isfinite(rsrp).any(axis=1)
        block = union_gaussian_kernel(rsrp, params.lte_alpha, params.lte_floor_dbm)
        kernel *= np.where(has[:, None] & has[None, :], block, 1.0)
    excluded = (walk_of[:, None] == walk_of[None, :]) & (
        np.abs(times[:, None] - times[None, :]) < params.same_walk_gap_ms
    )
    kernel[excluded] = -1.0
    n = min(params.neighbours, max(kernel.shape[1] - 1, 1))
    index = np.argsort(-kernel, axis=1, kind="stable")[:, :n]
    weights = np.take_along_axis(kernel, index, axis=1)
    weights = np.where(weights > 0, weights, 0.0)
    return walk_of, index, weights


def _visibility_kernel(counts: np.ndarray, alpha: float) -> np.ndarray:
    heard = counts.sum(axis=1) > 0
    if counts.shape[1] == 0 or not heard.any():
        return np.ones((counts.shape[0], counts.shape[0]))
    block = kl_kernel(visibility_multinomials(counts), alpha=alpha)
    kernel: np.ndarray = np.where(heard[:, None] & heard[None, :], block, 1.0)
    return kernel


def solve(walks: list[Walk], params: SignalGraphParams | None = None) -> Trajectories:
    """Raw PDR, recalibrated PDR (Eq. 4), GraphSLAM (motion + landmark edges) and SignalSLAM (plus signal
    edges, Eq. 7, iterated) positions of every walk's poses."""
    params = params or SignalGraphParams()
    raw = [np.vstack([w.start, dead_reckon(w.lengths, w.headings, w.start)]) for w in walks]
    calibrated = calibrated_positions(walks, prior=CalibrationPrior() if params.calibration_prior else None)
    graph = WalkGraph(walks, params)
    incremental = None
    if params.solver == "isam2":
        incremental = _Incremental(graph, graph.values(calibrated), params.chunk_poses)
        values = incremental.estimate()
    else:
        values = graph.optimise(graph.base, graph.values(calibrated))
    graphslam = graph.positions(values)
    if sum(w.window_t.size for w in walks) < 2:
        return Trajectories(raw, calibrated, graphslam, graphslam)
    _, index, weights = signal_neighbours(walks, params)
    pose_of_window = np.concatenate(
        [graph.offsets[i] + _nearest_pose(w.t_ms, w.window_t) for i, w in enumerate(walks)]
    )
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(params.signal_huber_k),
        gtsam.noiseModel.Isotropic.Sigma(2, params.signal_sigma_m * np.sqrt(params.signal_overlap)),
    )
    for _ in range(params.iterations):
        xy = np.vstack([values.atPose2(_key(int(k))).translation() for k in pose_of_window])
        edges = gtsam.NonlinearFactorGraph()
        for t in range(pose_of_window.size):
            total = weights[t].sum()
            if total <= 0:
                continue
            predicted = weights[t] @ xy[index[t]] / total  # Eq. 7
            edges.add(gtsam.PoseTranslationPrior2D(_key(int(pose_of_window[t])), predicted, noise))
        if incremental is not None:
            values = incremental.replace_signal_edges(edges)
        else:
            graph_s = gtsam.NonlinearFactorGraph(graph.base)
            graph_s.push_back(edges)
            values = graph.optimise(graph_s, values)
    return Trajectories(raw, calibrated, graphslam, graph.positions(values))


def _nearest_pose(pose_t: np.ndarray, window_t: np.ndarray) -> np.ndarray:
    i = np.clip(np.searchsorted(pose_t, window_t), 1, pose_t.size - 1)
    left_closer = (window_t - pose_t[i - 1]) <= (pose_t[i] - window_t)
    nearest: np.ndarray = np.where(left_closer, i - 1, i)
    return nearest


def position_at(t_ms: np.ndarray, positions: np.ndarray, query_t: np.ndarray) -> np.ndarray:
    """Linear interpolation of a walk's poses at the query times."""
    return np.column_stack([np.interp(query_t, t_ms, positions[:, k]) for k in (0, 1)])
