"""Building-anchor detectors on the server's sensor front-end: sensor patterns in, typed anchor observations
(time, type index, signature) out, one user at a time with state carried between batches.

- **Turns** (SemanticSLAM's and DynamicSLAM's most common organic anchor): the walking direction changes by
  at least ``turn_deg`` over ``turn_window_steps`` steps; then nothing for ``turn_refractory_steps``. No
  signature: turns are told apart by position, by the engine's maximum-likelihood association (Eq. 15-16).
- **Radio signatures**: a fixed Bluetooth beacon heard at ``beacon_dbm`` or more (identified by MAC), or a
  WiFi AP heard fresh at ``wifi_dbm`` or more (by BSSID): the phone is within a few metres of that
  transmitter (on the msindoor floor, readings >= -65 dBm of one beacon lie 3.0 m from their median position
  at p50, 7.8 m at p90). One observation per visit, at its strongest reading (the closest approach): the
  first strong reading would place the anchor at the edge of the strong zone, on the side the user came
  from. The signature makes the anchor identifiable, so the crowd map associates it by identity instead of
  by position.

- **Changes of floor** (elevators, stairs, escalators) from the barometer: ``slam_core.sensing.vertical``;
  without a barometer, lift rides from the accelerometer while the user stands: ``slam_core.sensing.lift``
  (the shared msindoor walks are single-floor and carry no barometer: neither fires there).
- **Magnetic anomalies** (organic anchors, SemanticSLAM): ``slam_core.sensing.magnetic``; off by default.

Type indices are the engine's (``server.ingestion.convert.ENGINE_ANCHOR_TYPES`` order). Pure numerics: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam_core.sensing.lift import LiftParams
from slam_core.sensing.lift import new_state as new_lift_state
from slam_core.sensing.magnetic import MagneticParams, MagneticState
from slam_core.sensing.vertical import VerticalParams, VerticalState
from slam_core.wifi.pairs import STALE_AP_MS


@dataclass(frozen=True)
class DetectorParams:
    turns: bool = False
    """Off by default: on the msindoor mall floor, turn anchors made the crowd replay worse (later half
    p50 / p90 2.76 / 5.98 m against 2.55 / 5.87 m without): a mall's corridor junctions are too alike and
    too close to be told apart by position at pedestrian-dead-reckoning accuracy."""
    beacons: bool = True
    wifi: bool = True
    turn_deg: float = 60.0
    turn_window_steps: int = 3
    turn_refractory_steps: int = 4
    beacon_dbm: float = -65.0
    wifi_dbm: float = -45.0
    visit_gap_ms: int = 10_000
    """A transmitter unheard above its threshold this long has been left: its next strong reading opens a
    new visit."""
    peak_drop_db: float = 3.0
    quiet_ms: int = 4_000
    stale_ap_ms: int = STALE_AP_MS
    """WiFi entries last seen longer ago than this before their scan are cached re-reports: ignored."""
    turn_type: int = 3
    beacon_type: int = 6
    wifi_type: int = 7
    vertical: VerticalParams = field(default_factory=VerticalParams)
    lift: LiftParams = field(default_factory=LiftParams)
    """Used only for users who have never sent pressure."""
    magnetic: MagneticParams = field(default_factory=MagneticParams)

    def __post_init__(self) -> None:
        if not (
            0.0 < self.turn_deg < 180.0 and self.turn_window_steps >= 1 and self.turn_refractory_steps >= 0
        ):
            raise ValueError(
                "turn_deg must be in (0, 180), turn_window_steps >= 1, turn_refractory_steps >= 0"
            )
        if self.visit_gap_ms <= 0 or self.stale_ap_ms < 0:
            raise ValueError("visit_gap_ms must be > 0 and stale_ap_ms >= 0")


@dataclass
class DetectorState:
    headings: list[float] = field(default_factory=list)  # the last steps' headings (ccw from east)
    steps_since_turn: int = 1_000_000
    visits: dict[str, _Visit] = field(default_factory=dict)  # signature -> its current visit
    vertical: VerticalState = field(default_factory=VerticalState)
    lift: np.ndarray = field(default_factory=new_lift_state)
    magnetic: MagneticState = field(default_factory=MagneticState)
    phone_finds_floors: bool = False
    """The phone has sent changes of floor of its own (a detection with a rise): the server's detector on
    its barometer keeps its state but reports nothing, or each change would count twice."""


@dataclass(frozen=True)
class AnchorEvents:
    t_ms: np.ndarray  # int64, sorted: when the detection became known
    type_index: np.ndarray  # int64
    signature: tuple[str, ...]  # "" for none
    observed_t_ms: np.ndarray  # int64: when the user was at the anchor (<= t_ms)
    rise_m: np.ndarray  # float: a change of floor's signed rise (up positive); NaN for the others

    @staticmethod
    def empty() -> AnchorEvents:
        return AnchorEvents(
            np.zeros(0, np.int64), np.zeros(0, np.int64), (), np.zeros(0, np.int64), np.zeros(0)
        )


def detect_turns(
    state: DetectorState, params: DetectorParams, step_t: np.ndarray, heading: np.ndarray
) -> list[int]:
    """Times of the steps completing a turn. ``heading``: each step's direction (rad, ccw from east, unwrapped
    or not); NaN headings are skipped."""
    fired = []
    limit = math.radians(params.turn_deg)
    for t, h in zip(step_t, heading, strict=True):
        if not math.isfinite(h):
            continue
        state.headings.append(float(h))
        del state.headings[: -(params.turn_window_steps + 1)]
        state.steps_since_turn += 1
        if len(state.headings) <= params.turn_window_steps:
            continue
        change = abs((state.headings[-1] - state.headings[0] + math.pi) % (2 * math.pi) - math.pi)
        if change >= limit and state.steps_since_turn > params.turn_refractory_steps:
            fired.append(int(t))
            state.steps_since_turn = 0
    return fired


@dataclass
class _Visit:
    type_index: int
    peak_t: int
    peak_rss: float
    last_t: int  # last reading at or above the threshold
    reported: bool = False


def _reading(
    state: DetectorState, params: DetectorParams, signature: str, type_index: int, t: int, rss: float,
    threshold: float, out: list[tuple[int, int, str, int]],
) -> None:  # fmt: skip
    """One reading of a transmitter: opens, extends or reports its visit (see ``detect_radio``)."""
    visit = state.visits.get(signature)
    if visit is not None and t - visit.last_t > params.visit_gap_ms:
        visit = None  # the previous visit ended (it was reported when it went quiet)
    if rss >= threshold:
        if visit is None:
            state.visits[signature] = _Visit(type_index, t, rss, t)
            return
        visit.last_t = t
        if rss > visit.peak_rss and not visit.reported:
            visit.peak_t, visit.peak_rss = t, rss
    if visit is not None and not visit.reported and rss <= visit.peak_rss - params.peak_drop_db:
        visit.reported = True
        out.append((t, visit.type_index, signature, visit.peak_t))


def _quiet(
    state: DetectorState, params: DetectorParams, now: int, out: list[tuple[int, int, str, int]]
) -> None:
    """Report visits that went quiet without a clear fall (the phone stopped hearing the transmitter)."""
    for signature, visit in list(state.visits.items()):
        if not visit.reported and now - visit.last_t >= params.quiet_ms:
            visit.reported = True
            out.append((now, visit.type_index, signature, visit.peak_t))
        if now - visit.last_t > params.visit_gap_ms:
            del state.visits[signature]  # bounded memory


def detect_radio(
    state: DetectorState,
    params: DetectorParams,
    scan_t: np.ndarray,
    scan_offsets: np.ndarray,
    scan_bssid: tuple[str, ...],
    scan_rss: np.ndarray,
    scan_last_seen: np.ndarray,
    beacon_t: np.ndarray,
    beacon_mac: tuple[str, ...],
    beacon_rss: np.ndarray,
) -> list[tuple[int, int, str, int]]:
    """(report time, type, signature, peak time) of each strong-transmitter visit whose closest approach
    became known in this batch. A visit opens at a reading >= the threshold; its peak is its strongest
    reading; it is reported once, when a reading falls ``peak_drop_db`` below the peak or when the
    transmitter has been quiet for ``quiet_ms``. The report comes after the peak, so it carries the peak's
    time: the tracker places the user at the peak by its dead reckoning since then."""
    out: list[tuple[int, int, str, int]] = []
    events: list[tuple[int, int, str, float, float]] = []  # (t, type, signature, rss, threshold)
    for k in range(scan_t.size if params.wifi else 0):
        t = int(scan_t[k])
        lo, hi = int(scan_offsets[k]), int(scan_offsets[k + 1])
        fresh = [
            i for i in range(lo, hi) if scan_last_seen[i] < 0 or scan_last_seen[i] >= t - params.stale_ap_ms
        ]
        for i in fresh:
            events.append(
                (t, params.wifi_type, wifi_signature(scan_bssid[i]), float(scan_rss[i]), params.wifi_dbm)
            )
    for k in range(beacon_t.size if params.beacons else 0):
        signature = f"beacon:{beacon_mac[k].lower()}"
        events.append(
            (int(beacon_t[k]), params.beacon_type, signature, float(beacon_rss[k]), params.beacon_dbm)
        )
    events.sort(key=lambda e: e[0])
    for t, type_index, signature, rss, threshold in events:
        if rss >= threshold or signature in state.visits:
            _reading(state, params, signature, type_index, t, rss, threshold, out)
    if events:
        _quiet(state, params, events[-1][0], out)
    return _one_per_place(out, params)


def wifi_signature(bssid: str) -> str:
    """One access point radiates several BSSIDs (per band and per SSID) that differ in the last hex digit:
    they share one signature, ``wifi:aa:bb:cc:dd:ee:f*``, so one place is one anchor."""
    return f"wifi:{bssid.lower()[:-1]}*"


def _one_per_place(
    out: list[tuple[int, int, str, int]], params: DetectorParams
) -> list[tuple[int, int, str, int]]:
    """One access point often serves several BSSIDs (bands, SSIDs) that peak together: of the WiFi reports
    with the same peak time only the first is kept (they would count one place several times)."""
    kept: list[tuple[int, int, str, int]] = []
    wifi_peaks: set[int] = set()
    for report in out:
        if report[1] == params.wifi_type:
            if report[3] in wifi_peaks:
                continue
            wifi_peaks.add(report[3])
        kept.append(report)
    return kept


def integrate_headings(azimuth: np.ndarray, turn: np.ndarray, start: float = 0.0) -> np.ndarray:
    """Each step's heading (ccw from east): from its azimuth (clockwise from north) when given, else the
    previous heading plus its turn; ``start`` is the heading before the first step."""
    out = np.empty(len(azimuth))
    previous = start
    for k in range(out.size):
        if math.isfinite(azimuth[k]):
            previous = math.pi / 2 - float(azimuth[k])
        elif math.isfinite(turn[k]):
            previous += float(turn[k])
        out[k] = previous
    return out


def step_headings(state: DetectorState, azimuth: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """``integrate_headings`` from the user's last step (the first relative step of a user counts from
    zero: only changes matter to the turn detector)."""
    return integrate_headings(azimuth, turn, state.headings[-1] if state.headings else 0.0)


def merge_events(
    turns: list[int],
    radio: list[tuple[int, int, str, int]],
    turn_type: int,
    floors: list[tuple[int, int, str, int, float]] | None = None,
) -> AnchorEvents:
    """One batch's detections in report order: (report time, type, signature, observed time) rows, and for
    ``floors`` (changes of floor and other events at a place) also the rise (NaN: none)."""
    nan = math.nan
    rows = sorted(
        [(t, turn_type, "", t, nan) for t in turns] + [(*r, nan) for r in radio] + (floors or []),
        key=lambda r: r[:4],
    )
    if not rows:
        return AnchorEvents.empty()
    return AnchorEvents(
        np.array([r[0] for r in rows], dtype=np.int64),
        np.array([r[1] for r in rows], dtype=np.int64),
        tuple(r[2] for r in rows),
        np.array([r[3] for r in rows], dtype=np.int64),
        np.array([r[4] for r in rows], dtype=float),
    )
