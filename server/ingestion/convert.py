"""The one module that sees both the wire models and the engine's arrays: batches in, estimates out."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from pydantic import ValidationError

from schemas.anchors import AnchorType, BuildingAnchor
from schemas.common import MAX_COORDINATE_M, Position
from schemas.estimates import EncounterEvent, EncounterModelName, Estimate, EstimateSource
from schemas.sensors import (
    AnchorReading,
    BeaconSighting,
    GpsFix,
    Landmark,
    PeerSighting,
    PositionFix,
    RotationVectorStream,
    SensorBatch,
    TagReading,
    Vector3Stream,
    WifiScan,
)
from server.errors import InvalidInputError
from server.ingestion import transport
from server.ingestion.extent import Extent
from server.ingestion.transport import PackedBatch
from slam_core.encounters.models import MODEL_BLUETOOTH, MODEL_WIFI_FINGERPRINT
from slam_core.geo import GeoFrame
from slam_core.sensing.pdr.online import ImuSamples
from slam_core.tracking.batches import check_values
from slam_core.tracking.tracker import BuildingTracker, EncounterResult, EstimateRow, UserBatch

ENGINE_ANCHOR_TYPES: tuple[AnchorType, ...] = tuple(AnchorType)
"""The engine's anchor type index of each wire type (the first five are the paper testbed's)."""
_TYPE_INDEX = {t: i for i, t in enumerate(ENGINE_ANCHOR_TYPES)}
TAG_SIGMA_M = 0.5
"""A tag with an encoded position places the phone within about an arm's length of it."""


class KnownPlace(NamedTuple):
    """Where an operator pinned an anchor: its place in local metres and its floor."""

    x_m: float
    y_m: float
    floor: int


@dataclass(frozen=True)
class BuildingContext:
    """What placing a batch's landmarks needs of its building. ``building_context`` builds it from the
    building's tracker wherever a batch is converted (the live path, recovery, the evaluation, the replays):
    a field left out would place a landmark wrongly, so none has a default."""

    building_id: str
    geo: GeoFrame | None
    extent: Extent | None
    """Where positions may be (None: anywhere the schema allows); a fix, GPS fix or tag outside it refuses
    the batch."""
    floors: frozenset[int]
    """The building's floors: a landmark on another floor refuses the batch."""
    known_anchors: Mapping[str, KnownPlace]
    """The live anchors operators pinned, by public id: where an anchor reading places the phone."""
    anchor_sigma_m: float
    """How far from a known anchor a phone that reads it may be (the filter's anchor detection sigma)."""


def building_context(
    building_id: str,
    tracker: BuildingTracker,
    public_ids: Mapping[str, int],
    geo: GeoFrame | None,
    extent: Extent | None,
) -> BuildingContext:
    """The one way a building's conversion context is made: its floors and its pinned anchors (named by
    ``public_ids``, public id -> crowd index) as its tracker holds them now."""
    crowd = tracker.crowd
    known = {}
    for public_id, index in public_ids.items():
        if crowd.is_live(index):
            mean, _, _, is_known, _, _ = crowd.anchor(index)
            if is_known:
                known[public_id] = KnownPlace(float(mean[0]), float(mean[1]), crowd.level(index))
    return BuildingContext(
        building_id,
        geo,
        extent,
        frozenset(tracker.levels),
        known,
        tracker.params.filter.anchors.detection_sigma_m,
    )


@dataclass(frozen=True)
class Converted:
    user_batch: UserBatch
    warnings: list[str]


def anchor_type_index(anchor_type: AnchorType) -> int:
    return _TYPE_INDEX[anchor_type]


def packed(batch: SensorBatch) -> PackedBatch:
    """The front's half of a batch's conversion, the same in every mode: its sensors as the packed columns
    its building receives (``server.ingestion.transport``), its landmarks left for the building to place
    (``placed``), as only the building knows its frame, extent, floors and known anchors. Raises
    ``ValueError`` where ``UserBatch``'s checks would.

    The batches phones send most (no raw IMU or barometer: the phone counts its own steps) are packed
    straight from the wire model's values, without the ~25 small arrays in between."""
    if batch.pressure is not None or _has_raw_imu(batch):
        return transport.pack(sensor_arrays(batch))
    ints, floats, strings = _sensor_columns(batch)
    lengths = floats["step_length"]
    check_values(batch.effective_user_id, (lengths, floats["scan_rss"], floats["peer_rss"]), (), lengths)
    return transport.pack_lists(batch.effective_user_id, batch.ble_advertised_id, ints, floats, strings)


def placed(columns: PackedBatch, landmarks: Sequence[Landmark], ctx: BuildingContext) -> Converted:
    """The building's half: the front's columns as engine arrays, with the batch's landmarks placed in the
    building's frame (a landmark that cannot be placed skipped with a warning saying why). Raises
    ``ValueError`` for a landmark outside the building's extent or on a floor it does not have."""
    user_batch = transport.unpack(columns)
    if not landmarks:
        return Converted(user_batch, [])
    fixes, warnings = landmark_fixes(landmarks, ctx)
    # the unpacked batch is this call's own: its fixes set in place and the whole batch checked once
    # (``dataclasses.replace`` built it field by field again, half of a first batch's conversion)
    user_batch.__dict__.update(fixes)
    user_batch.__post_init__()
    return Converted(user_batch, warnings)


def to_user_batch(batch: SensorBatch, ctx: BuildingContext) -> Converted:
    """The batch as engine arrays, converted by the same two halves as the live path (``packed`` at the
    front, ``placed`` in the building), so that recovery, the evaluation and the replays see what the
    server saw."""
    return placed(packed(batch), batch.landmarks, ctx)


def sensor_arrays(batch: SensorBatch) -> UserBatch:
    """The batch's sensors as engine arrays, its landmarks left out: what ``packed`` packs (straight from
    the wire model's values where it can). Raises ``ValueError`` as ``UserBatch`` does."""
    ints, floats, strings = _sensor_columns(batch)
    fields: dict[str, Any] = {
        "user": batch.effective_user_id,
        "ble_id": batch.ble_advertised_id,
        **_NO_FIXES,
        **{name: _ints(values) for name, values in ints.items()},
        **{name: _floats(values) for name, values in floats.items()},
        **strings,
        "imu": _imu(batch),
    }
    return UserBatch(**fields)


def landmark_fixes(landmarks: Sequence[Landmark], ctx: BuildingContext) -> tuple[dict[str, Any], list[str]]:
    """The landmarks as ``UserBatch``'s fix fields, and a warning for each that cannot be placed. Raises
    ``ValueError`` for a landmark outside the building's extent or on a floor it does not have."""
    warnings: list[str] = []
    fix_t: list[int] = []
    fix_xy: list[tuple[float, float]] = []
    fix_sigma: list[float] = []
    fix_azimuth: list[float] = []
    fix_level: list[int] = []
    for i, mark in enumerate(landmarks):
        placed = _place(mark, ctx)
        if isinstance(placed, str):
            warnings.append(f"landmarks.{i}: {placed}")
            continue
        (x, y), sigma, azimuth, level = placed
        if ctx.extent is not None and (refusal := ctx.extent.refusal(f"landmarks.{i}", x, y)) is not None:
            raise ValueError(refusal)
        if level not in ctx.floors:
            raise ValueError(
                f"landmarks.{i}: building {ctx.building_id!r} has no floor {level}; its floors: "
                f"{', '.join(map(str, sorted(ctx.floors)))}"
            )
        fix_t.append(mark.t_ms)
        fix_xy.append((x, y))
        fix_sigma.append(sigma)
        fix_azimuth.append(azimuth)
        fix_level.append(level)
    fixes: dict[str, Any] = {
        "fix_t": _ints(fix_t),
        "fix_xy": np.array(fix_xy, dtype=np.float64).reshape(-1, 2) if fix_xy else _NO_XY,
        "fix_sigma": _floats(fix_sigma),
        "fix_azimuth": _floats(fix_azimuth),
        "fix_level": _ints(fix_level) if any(fix_level) else _NO_INTS,
    }
    return fixes, warnings


def _sensor_columns(
    batch: SensorBatch,
) -> tuple[dict[str, list[int]], dict[str, list[float]], dict[str, tuple[str, ...]]]:
    """The batch's steps, detections, scans and sightings as ``UserBatch``'s fields, as lists (integers,
    floats, strings): the one place both conversions read them."""
    steps = batch.steps
    scans = batch.wifi_scans
    aps = [ap for s in scans for ap in s.aps]
    peers = [s for s in batch.bluetooth if isinstance(s, PeerSighting)]
    beacons = [s for s in batch.bluetooth if isinstance(s, BeaconSighting)]
    detections = batch.anchor_detections
    ints = {
        "step_t": [s.t_ms for s in steps],
        "detect_t": [d.t_ms for d in detections],
        "detect_type": [anchor_type_index(d.type) for d in detections],
        "scan_t": [s.t_ms for s in scans],
        "scan_offsets": _offsets(scans),
        "scan_last_seen": [-1 if ap.last_seen_ms is None else ap.last_seen_ms for ap in aps],
        "peer_t": [p.t_ms for p in peers],
        "beacon_t": [s.t_ms for s in beacons],
    }
    floats = {
        "step_length": [s.length_m for s in steps],
        "step_azimuth": [_nan_if_none(s.azimuth_rad) for s in steps],
        "step_turn": [_nan_if_none(s.heading_change_rad) for s in steps],
        "scan_rss": [ap.rssi_dbm for ap in aps],
        "peer_rss": [p.rssi_dbm for p in peers],
        "beacon_rss": [s.rssi_dbm for s in beacons],
        # only when a detection carries a rise (a change of floor): most batches have none
        "detect_rise": (
            [_nan_if_none(d.rise_m) for d in detections]
            if any(d.rise_m is not None for d in detections)
            else []
        ),
    }
    strings = {
        "scan_bssid": tuple(ap.bssid.lower() for ap in aps),  # one AP whatever case a phone writes
        "peer_id": tuple(p.peer_advertised_id for p in peers),
        "beacon_mac": tuple(s.mac for s in beacons),
    }
    return ints, floats, strings


# Shared empty arrays: most batches carry no fix, detection or beacon, and an array per absent field had
# cost a fifth of the conversion. Nothing can be written into an empty array; they stay writable so that
# the numba kernels see one array type (a read-only array is another type to them, compiled anew).
_NO_INTS = np.zeros(0, dtype=np.int64)
_NO_FLOATS = np.zeros(0, dtype=np.float64)
_NO_XY = np.zeros((0, 2), dtype=np.float64)
_NO_FIXES: dict[str, Any] = {
    "fix_t": _NO_INTS,
    "fix_xy": _NO_XY,
    "fix_sigma": _NO_FLOATS,
    "fix_azimuth": _NO_FLOATS,
    "fix_level": _NO_INTS,
}
"""``landmark_fixes`` of no landmarks."""


def _ints(values: list[int]) -> np.ndarray:
    return np.array(values, dtype=np.int64) if values else _NO_INTS


def _floats(values: list[float]) -> np.ndarray:
    return np.array(values, dtype=np.float64) if values else _NO_FLOATS


def _offsets(scans: list[WifiScan]) -> list[int]:
    """Where each scan's APs start among all of them, and their total last ([0] without scans). Summed
    here: ``np.cumsum`` of a short list costs more than the list."""
    offsets = [0]
    for scan in scans:
        offsets.append(offsets[-1] + len(scan.aps))
    return offsets


def _nan_if_none(value: float | None) -> float:
    return math.nan if value is None else value


def _vector(stream: Vector3Stream | None) -> np.ndarray:
    if stream is None:
        return np.zeros((0, 4))
    return np.column_stack([stream.t_ms, stream.x, stream.y, stream.z]).astype(np.float64)


def _rotation(stream: RotationVectorStream | None) -> np.ndarray:
    if stream is None:
        return np.zeros((0, 5))
    w = np.full(len(stream.t_ms), np.nan) if stream.w is None else stream.w
    return np.column_stack([stream.t_ms, stream.x, stream.y, stream.z, w]).astype(np.float64)


def _has_raw_imu(batch: SensorBatch) -> bool:
    """Whether the batch carries IMU for the PDR front-end: not when the phone counts its own steps, nor
    without any accelerometer, gyroscope or rotation stream."""
    if batch.steps:
        return False
    streams = (batch.accelerometer, batch.rotation_vector, batch.game_rotation_vector, batch.gyroscope)
    return any(s is not None for s in streams)


def _imu(batch: SensorBatch) -> ImuSamples | None:
    """Raw IMU for the PDR front-end (orientation streams alone are still kept so the next batch's samples
    have a held orientation), or only the barometer when the phone counts its own steps (the server finds
    the changes of floor in it); None when there is neither."""
    pressure = (
        np.zeros((0, 2))
        if batch.pressure is None
        else np.column_stack([batch.pressure.t_ms, batch.pressure.value]).astype(np.float64)
    )
    if not _has_raw_imu(batch):
        return ImuSamples(acc=np.zeros((0, 4)), pressure=pressure) if pressure.size else None
    return ImuSamples(
        acc=_vector(batch.accelerometer),
        gyr=_vector(batch.gyroscope),
        mag=_vector(batch.magnetometer),
        rv=_rotation(batch.rotation_vector),
        grv=_rotation(batch.game_rotation_vector),
        pressure=pressure,
    )


def _place(
    mark: GpsFix | TagReading | AnchorReading | PositionFix, ctx: BuildingContext
) -> tuple[tuple[float, float], float, float, int] | str:
    """((x, y), sigma, azimuth or NaN, floor) of a landmark in local metres, or why it cannot be placed. A GPS
    fix is taken on floor 0 (where GPS reaches: the entrances); a tag without a floor, too."""
    if isinstance(mark, PositionFix):
        azimuth = math.nan if mark.azimuth_rad is None else mark.azimuth_rad
        return (mark.position.x_m, mark.position.y_m), mark.sigma_m, azimuth, mark.floor
    if isinstance(mark, AnchorReading):
        known = ctx.known_anchors.get(mark.anchor_id)
        if known is None:
            return f"anchor {mark.anchor_id!r} is not a known anchor of building {ctx.building_id!r}"
        return (known.x_m, known.y_m), ctx.anchor_sigma_m, math.nan, known.floor
    if isinstance(mark, GpsFix):
        if ctx.geo is None:
            return f"building {ctx.building_id!r} has no geo-reference, so a GPS fix cannot be placed"
        return ctx.geo.to_local(mark.lat_deg, mark.lon_deg), mark.accuracy_m, math.nan, 0
    encoded = mark.encoded_position()
    if encoded is None:
        return "the tag encodes no position (tags without one are kept for SignalSLAM loop closures)"
    if ctx.geo is None:
        return f"building {ctx.building_id!r} has no geo-reference, so the tag's position cannot be placed"
    lat, lon, level = encoded
    return ctx.geo.to_local(lat, lon), TAG_SIGMA_M, math.nan, level


def estimate(
    row: EstimateRow,
    building_id: str,
    user_id: str,
    device_id: str,
    geo: GeoFrame | None,
    source: EstimateSource,
) -> Estimate:
    """The wire estimate of an engine row, validated by the schema (finite numbers, heading within the
    wrapped range, a symmetric positive semi-definite covariance, WGS-84 bounds): a ``ValueError`` naming the
    user when the engine's numbers break it. One validation of a plain dict in pydantic's core: cheaper
    than constructing the three models with the same checks written out by hand."""
    lat = lon = None
    if geo is not None:
        lat, lon = geo.to_wgs84(row.x, row.y)
    xx, xy, yy = row.cov
    try:
        built: Estimate = _validate_estimate(
            {
                "building_id": building_id,
                "user_id": user_id,
                "device_id": device_id,
                "t_ms": row.t_ms,
                "position": {"x_m": row.x, "y_m": row.y},
                "covariance_m2": [[xx, xy], [xy, yy]],
                "best_particle": {"x_m": row.best[0], "y_m": row.best[1]},
                "heading_rad": (row.heading + math.pi) % (2 * math.pi) - math.pi,
                "floor": row.floor,
                "floor_probability": row.floor_probability,
                "source": source,
                "lat_deg": lat,
                "lon_deg": lon,
            }
        )
    except ValidationError as exc:
        if all(_out_of_range(e) for e in exc.errors()):
            # finite, but beyond where positions may be: the batch walked its user there, and is refused
            raise InvalidInputError(
                f"the batch would take user {user_id!r} to ({row.x:.0f}, {row.y:.0f}) m from the building's "
                f"origin, beyond the {MAX_COORDINATE_M:g} m (or the WGS-84 range) positions may have"
            ) from None
        raise ValueError(f"the engine's estimate of {user_id!r} breaks the schema: {exc}") from None
    return built


_RANGE_ERRORS = frozenset({"less_than_equal", "greater_than_equal", "less_than", "greater_than"})


def _out_of_range(error: Any) -> bool:
    """A validation error of a finite position (local or WGS-84) beyond its bounds."""
    loc = error.get("loc", ())
    return (
        error.get("type") in _RANGE_ERRORS
        and bool(loc)
        and loc[0]
        in (
            "position",
            "best_particle",
            "lat_deg",
            "lon_deg",
        )
    )


_validate_estimate = Estimate.__pydantic_validator__.validate_python
_validate_encounter = EncounterEvent.__pydantic_validator__.validate_python

_ENCOUNTER_MODELS = {
    MODEL_BLUETOOTH: EncounterModelName.BLUETOOTH,
    MODEL_WIFI_FINGERPRINT: EncounterModelName.WIFI_FINGERPRINT,
}


def _places(places: tuple[float, ...] | None) -> dict[str, dict[str, float]]:
    """The two users' positions at the encounter, where known and on the map (a carried estimate far off the
    map is left out rather than refusing the event)."""
    if places is None or not all(math.isfinite(v) and abs(v) <= MAX_COORDINATE_M for v in places):
        return {}
    xa, ya, xb, yb = places
    return {"position_a": {"x_m": xa, "y_m": ya}, "position_b": {"x_m": xb, "y_m": yb}}


def encounter_event(result: EncounterResult, building_id: str) -> EncounterEvent:
    """The wire event of a chosen detection, its range and sigma clamped to the schema's 200 m and validated
    by it (as ``estimate``)."""
    d = result.detection
    try:
        event: EncounterEvent = _validate_encounter(
            {
                "building_id": building_id,
                "t_ms": int(d.t_ms),
                "user_a": d.user_a,
                "user_b": d.user_b,
                "model": _ENCOUNTER_MODELS.get(d.model, EncounterModelName.WIFI_EQ3),
                "distance_m": min(float(d.distance_m), 200.0),
                "distance_sigma_m": min(math.sqrt(d.variance_m2), 200.0) if d.variance_m2 > 0.0 else math.nan,
                "applied": bool(result.applied),
                "floor": int(result.level),
                **_places(result.places),
            }
        )
    except ValidationError as exc:
        raise ValueError(
            f"the encounter of {d.user_a!r} and {d.user_b!r} has no valid range: "
            f"{d.distance_m} m, variance {d.variance_m2} m^2 ({exc.error_count()} schema errors)"
        ) from None
    return event


def building_anchor(
    public_id: str,
    building_id: str,
    mean: np.ndarray,
    cov: np.ndarray,
    type_index: int,
    known: bool,
    observations: int,
    last_seen_ms: int | None,
    label: str | None = None,
    floor: int = 0,
    signature: str | None = None,
) -> BuildingAnchor:
    sym = 0.5 * (cov[0, 1] + cov[1, 0])
    return BuildingAnchor(
        id=public_id,
        building_id=building_id,
        floor=floor,
        type=ENGINE_ANCHOR_TYPES[type_index],
        position=Position(x_m=float(mean[0]), y_m=float(mean[1])),
        covariance_m2=[[float(cov[0, 0]), float(sym)], [float(sym), float(cov[1, 1])]],
        observation_count=observations,
        known=known,
        label=label,
        last_seen_ms=last_seen_ms,
        signature=signature,
    )
