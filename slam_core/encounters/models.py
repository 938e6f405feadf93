"""Encounter models (DynamicSLAM Section 4.1.2) behind a name registry.

- ``wifi-eq3``: Eq. 3, Sim = ||U1 - U2|| / n over the n APs common to both scans' strongest N (Table 2:
  N = 5), an encounter when Sim < 8 dB; relative distance from the logarithmic fit d = a + b ln(Sim)
  (Figure 3).
- ``bluetooth``: RSS above the -90 dBm cut-off (Table 2) is an encounter; distance from the quadratic fit
  d = c0 + c1 RSS + c2 RSS^2 (Figure 2).

Each model's fit also gives R, the variance of the distance it reports (the residual variance of the fit).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property, lru_cache
from typing import Any

import numpy as np

from slam_core.wifi.pairs import STALE_AP_MS
from slam_core.wifi.similarity import eq3

FIT_MAX_DISTANCE_M = 25.0
"""Range models are fitted on labelled pairs up to 25 m, about three times the range within which encounters
are applied (``slam_core.encounters.selection``)."""


@dataclass(frozen=True)
class WifiEq3Params:
    strongest_n: int = 5  # Table 2
    threshold_db: float = 8.0  # Table 2
    min_common: int = 1


@dataclass(frozen=True)
class BluetoothParams:
    cutoff_dbm: float = -90.0  # Table 2


@dataclass(frozen=True)
class WifiFingerprintParams:
    """Our WiFi encounter model (beyond the paper): the RMS dB difference over the *union* of both scans'
    fresh APs, an AP missing from one counting as ``floor_dbm`` (``slam_core.wifi.pairs``). On the msindoor
    floor it reaches precision 0.32 at recall 0.5 for pairs within 5 m, where Eq. 3 reaches 0.20; 10 dB is a
    strict threshold (pairs passing it: 73 % within 5 m, median 3.1 m)."""

    threshold_db: float = 10.0
    floor_dbm: float = -100.0


def strongest(rss: np.ndarray, n: int) -> np.ndarray:
    """Indices of the ``n`` strongest heard entries (NaN = not heard)."""
    heard = np.flatnonzero(~np.isnan(rss))
    if heard.size <= n:
        return heard
    return heard[np.argsort(-rss[heard], kind="stable")[:n]]


def wifi_eq3_similarity(rss_a: np.ndarray, rss_b: np.ndarray, params: WifiEq3Params) -> tuple[float, int]:
    """Eq. 3 (``slam_core.wifi.similarity.eq3``) on two scans given as dense RSS vectors over the same APs
    (NaN = not heard): (Sim in dB, n common). Returns (inf, n) when fewer than ``min_common`` APs are
    common."""
    top_a, top_b = strongest(rss_a, params.strongest_n), strongest(rss_b, params.strongest_n)
    sim, n = eq3(top_a, rss_a[top_a], top_b, rss_b[top_b])
    if n < params.min_common:
        return math.inf, n
    return sim, n


@dataclass(frozen=True)
class RangeModel:
    """The paper's model families fitted as measurement models, feature = f(distance), then inverted:
    ``wifi-log``: Sim = a + b ln d (Figure 3's logarithmic model); ``bt-quadratic``: RSS = c0 + c1 ln d +
    c2 (ln d)^2 (Figure 2's quadratic fit, in log-distance).

    Departure from the paper: fitting distance as a function of the feature regresses every reading to the
    mean of the calibration distances, so a close pair with a middling reading is pushed apart. Inverting the
    forward fit gives the maximum-likelihood range, and its variance R = (sigma_f / |f'(d)|)^2 grows where
    the feature stops changing with distance, so far-away detections carry almost no weight.
    """

    kind: str
    coefficients: tuple[float, ...]
    sigma: float  # residual standard deviation of the feature (dB)
    min_distance: float = 0.5
    max_distance: float = 60.0
    bin_edges: tuple[float, ...] = ()
    bin_mse: tuple[float, ...] = ()
    """Empirical mean squared range error per bin of the reported range, measured on the labelled pairs the
    tracker would apply (detected, and within the selection range); R is never below it (the analytic
    variance alone is overconfident where the feature is ambiguous)."""

    def with_empirical_variance(
        self, feature: np.ndarray, distance: np.ndarray, min_per_bin: int = 30
    ) -> RangeModel:
        """Bins of reported range (finer where ranges are short), merged upwards until each holds
        ``min_per_bin`` labelled pairs; each bin's R floor is its mean squared range error."""
        z, _ = self.range_and_variance(feature)
        err2 = (z - np.asarray(distance, dtype=float)) ** 2
        bounds = [0.0, 1.5, 3.0, 4.5, 6.0, 8.0, 11.0, 15.0, 20.0, 30.0, 45.0, np.inf]
        edges: list[float] = []
        mse: list[float] = []
        lo = 0
        for hi in range(1, len(bounds)):
            in_bin = (z >= bounds[lo]) & (z < bounds[hi])
            if in_bin.sum() >= min_per_bin or (hi == len(bounds) - 1 and in_bin.any()):
                edges.append(bounds[lo])
                mse.append(float(np.mean(err2[in_bin])))
                lo = hi
        if not mse:
            edges, mse = [0.0], [float(np.mean(err2))]
        return replace(self, bin_edges=tuple(edges), bin_mse=tuple(mse))

    def feature_at(self, distance: np.ndarray) -> np.ndarray:
        x = np.log(np.maximum(np.asarray(distance, dtype=float), 1e-3))
        values: np.ndarray = np.polynomial.polynomial.polyval(x, self.coefficients)
        return values

    @cached_property
    def _inverse_table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(feature, distance) of the monotone envelope, ready for interpolation, and |slope| on the grid."""
        grid = np.geomspace(self.min_distance, self.max_distance, 400)
        f = self.feature_at(grid)
        # monotone envelope: Sim grows with distance, RSS falls with it
        increasing = self.kind == "wifi-log"
        mono = np.maximum.accumulate(f) if increasing else np.minimum.accumulate(f)
        xs, ds = (mono, grid) if increasing else (mono[::-1], grid[::-1])
        return xs, ds, grid, np.abs(np.gradient(mono, grid))

    def range_and_variance(self, feature: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The maximum-likelihood range of each reading and its variance R (m^2)."""
        xs, ds, _, _ = self._inverse_table
        d = np.interp(np.asarray(feature, dtype=float), xs, ds)
        return d, self.variance_at_distance(d)

    def variance_at_distance(self, distance: np.ndarray) -> np.ndarray:
        """R at a range: (sigma_f / |f'(d)|)^2, never below the bin's empirical floor nor 0.25 m^2."""
        _, _, grid, slope = self._inverse_table
        d = np.clip(np.asarray(distance, dtype=float), self.min_distance, self.max_distance)
        s = np.maximum(np.interp(d, grid, slope), self.sigma / self.max_distance)
        variance = np.minimum((self.sigma / s) ** 2, self.max_distance**2)
        if self.bin_mse:
            k = np.clip(
                np.searchsorted(np.asarray(self.bin_edges), d, side="right") - 1, 0, len(self.bin_mse) - 1
            )
            variance = np.maximum(variance, np.asarray(self.bin_mse)[k])
        floored: np.ndarray = np.maximum(variance, 0.25)
        return floored

    def sigma_reach(self, max_sigma_m: float, up_to_m: float) -> float:
        """The farthest distance, up to ``up_to_m``, at which the range's standard deviation is at most
        ``max_sigma_m`` (rounded up, never down: beyond it no distance up to ``up_to_m`` passes); 0 when none
        does. An encounter whose predicted distance exceeds it cannot be chosen
        (``slam_core.encounters.selection``)."""
        return _sigma_reach(self, max_sigma_m, up_to_m)


@lru_cache(maxsize=64)
def _sigma_reach(model: RangeModel, max_sigma_m: float, up_to_m: float) -> float:
    """``RangeModel.sigma_reach``. The variance is monotone between the slope table's points and constant
    within each empirical bin, so on every piece between those points it passes on an interval that holds an
    end of the piece: evaluating the ends (and a 1 cm grid) finds the last passing point, and the next point
    evaluated bounds the distances that pass."""
    _, _, grid, _ = model._inverse_table
    points = np.unique(
        np.concatenate(
            [
                np.arange(0.0, up_to_m, 0.01),
                grid[grid < up_to_m],
                [e for e in model.bin_edges if e < up_to_m],
                [model.min_distance, up_to_m],
            ]
        )
    )
    points = points[points <= up_to_m]
    passing = np.flatnonzero(np.sqrt(model.variance_at_distance(points)) <= max_sigma_m)
    if passing.size == 0:
        return 0.0
    last = int(passing[-1])
    return float(points[last + 1]) if last + 1 < points.size else float(up_to_m)


@dataclass(frozen=True)
class Calibration:
    """The fitted range models of a building's radio environment (the paper's Figures 2-3)."""

    wifi: RangeModel
    bluetooth: RangeModel
    wifi_fingerprint: RangeModel | None = None
    """The union-fingerprint feature's range model (``crowdslam calibrate`` fits it); needed only when the
    ``wifi-fingerprint`` encounter model is chosen."""

    def to_dict(self) -> dict[str, Any]:
        out = {"wifi": asdict(self.wifi), "bluetooth": asdict(self.bluetooth)}
        if self.wifi_fingerprint is not None:
            out["wifi_fingerprint"] = asdict(self.wifi_fingerprint)
        return out

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> Calibration:
        """Inverse of ``to_dict``; a missing or malformed model raises ValueError naming it."""
        models: list[RangeModel | None] = []
        optional = {"wifi_fingerprint"}
        for name, kind in (
            ("wifi", "wifi-log"),
            ("bluetooth", "bt-quadratic"),
            ("wifi_fingerprint", "wifi-log"),
        ):
            if name in optional and raw.get(name) is None:
                models.append(None)
                continue
            try:
                entry = dict(raw[name])
                model = RangeModel(
                    kind=str(entry["kind"]),
                    coefficients=tuple(float(c) for c in entry["coefficients"]),
                    sigma=float(entry["sigma"]),
                    min_distance=float(entry.get("min_distance", 0.5)),
                    max_distance=float(entry.get("max_distance", 60.0)),
                    bin_edges=tuple(float(e) for e in entry.get("bin_edges", ())),
                    bin_mse=tuple(float(e) for e in entry.get("bin_mse", ())),
                )
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"calibration: the {name} model is missing or malformed ({exc})") from None
            if model.kind != kind or len(model.bin_edges) != len(model.bin_mse) or model.sigma <= 0:
                raise ValueError(f"calibration: the {name} model must be a valid {kind} range model")
            if not all(math.isfinite(c) for c in (*model.coefficients, *model.bin_mse, *model.bin_edges)):
                raise ValueError(f"calibration: the {name} model has non-finite numbers")
            models.append(model)
        wifi, bluetooth, fingerprint = models
        if wifi is None or bluetooth is None:  # unreachable: both are required above
            raise ValueError("calibration: the wifi and bluetooth models are required")
        return cls(wifi, bluetooth, fingerprint)


def fit_range_model(
    feature: np.ndarray, distance: np.ndarray, kind: str, max_distance_m: float = math.inf
) -> RangeModel:
    """Least-squares fit of feature = f(distance) on labelled pairs, those farther than ``max_distance_m``
    left out: far beyond where encounters are used, the receiver's sensitivity cuts off the weak readings
    and the ones left flatten the fit (on the testbed, Bluetooth ranges read 1-2 m long at 15-30 m)."""
    feature = np.asarray(feature, dtype=float)
    distance = np.asarray(distance, dtype=float)
    ok = np.isfinite(feature) & np.isfinite(distance) & (distance > 0) & (distance <= max_distance_m)
    feature, distance = feature[ok], distance[ok]
    if feature.size < 10:
        raise ValueError(f"need at least 10 labelled pairs to fit the {kind} model, got {feature.size}")
    x = np.log(np.maximum(distance, 0.1))
    if kind == "wifi-log":
        design = np.column_stack([np.ones_like(x), x])
    elif kind == "bt-quadratic":
        design = np.column_stack([np.ones_like(x), x, x * x])
    else:
        raise ValueError(f"unknown range model {kind!r}; valid: wifi-log, bt-quadratic")
    coef, *_ = np.linalg.lstsq(design, feature, rcond=None)
    sigma = float(np.sqrt(np.mean((feature - design @ coef) ** 2)))
    return RangeModel(kind, tuple(float(c) for c in coef), max(sigma, 0.5))


ENCOUNTER_MODELS: dict[str, Callable[..., object]] = {
    "wifi-eq3": WifiEq3Params,
    "wifi-fingerprint": WifiFingerprintParams,
    "bluetooth": BluetoothParams,
}


def encounter_model(name: str, **kwargs: float) -> object:
    """Parameters of a named encounter model; an unknown name lists the valid ones."""
    try:
        factory = ENCOUNTER_MODELS[name]
    except KeyError:
        raise ValueError(f"unknown encounter model {name!r}; valid: {', '.join(ENCOUNTER_MODELS)}") from None
    return factory(**kwargs)


MODEL_WIFI = 0
MODEL_BLUETOOTH = 1
MODEL_WIFI_FINGERPRINT = 2
WIFI_MODELS = ("wifi-eq3", "wifi-fingerprint")


@dataclass(frozen=True)
class DetectionParams:
    wifi: WifiEq3Params = field(default_factory=WifiEq3Params)
    bluetooth: BluetoothParams = field(default_factory=BluetoothParams)
    scan_pair_window_ms: int = 1_000
    bt_smoothing_ms: int = 1_000
    """One sighting period: a longer window blurs the range of pairs walking towards each other."""
    stale_ap_ms: int = STALE_AP_MS
    """Beyond the paper: scans re-report cached APs (on real phones 50-60 % of entries are older than 3 s);
    entries whose last-seen time is more than this before the scan are dropped before Eq. 3."""
    retention_ms: int = 10_000
    """Scans and sightings older than this (behind the newest time seen) are forgotten."""
    late_scan_ms: int = 2_000
    """A scan more than this behind the newest scan when it arrives (a delayed batch) is compared directly
    rather than through the index (``slam_core.encounters.search``): it bounds how far back an index walk
    goes."""
    wifi_model: str = "wifi-eq3"
    """``wifi-eq3`` (the paper) or ``wifi-fingerprint`` (ours: union RMS, ``WifiFingerprintParams``; needs
    its range model in the calibration). Candidates are found by the same strongest-N index either way."""
    fingerprint: WifiFingerprintParams = field(default_factory=WifiFingerprintParams)

    def __post_init__(self) -> None:
        if self.bt_smoothing_ms <= 0:
            raise ValueError("bt_smoothing_ms must be > 0")
        if self.wifi_model not in WIFI_MODELS:
            raise ValueError(
                f"unknown WiFi encounter model {self.wifi_model!r}; valid: {', '.join(WIFI_MODELS)}"
            )
