"""A batch's one shape from the front to its building: its columns packed by the front (every field comes
back equal, with the dtype, shape and numba type a conversion gives: another type would compile the kernels
anew; writable) and its landmarks, which the building alone can place."""

from __future__ import annotations

import dataclasses
import math
import pickle
import re
from typing import Any

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.sensors import SensorBatch
from server.buildings.submissions import BatchHeader, Submission, batch_fields, received_batch
from server.errors import InvalidInputError
from server.ingestion import convert
from server.ingestion import transport as batch_transport
from server.ingestion.extent import Extent
from slam_core.geo import GeoFrame
from slam_core.sensing.pdr.online import ImuSamples
from slam_core.tracking.tracker import UserBatch

T0 = 1_700_000_000_000


def _sensor_batch(**extra: Any) -> SensorBatch:
    body: dict[str, Any] = {"building_id": "hq", "device_id": "phone-1", "batch_id": "b-1", "seq": 4}
    return SensorBatch.model_validate(body | extra)


def _walking_batch() -> SensorBatch:
    return _sensor_batch(
        ble_advertised_id="ble-1",
        steps=[
            {"t_ms": T0 + 100, "length_m": 0.7, "azimuth_rad": 0.5},
            {"t_ms": T0 + 600, "length_m": 0.72, "heading_change_rad": -0.1},
        ],
        wifi_scans=[
            {
                "t_ms": T0 + 200,
                "aps": [
                    {"bssid": "02:00:00:00:00:01", "rssi_dbm": -61.5, "frequency_mhz": 2437},
                    {"bssid": "02:00:00:00:00:02", "rssi_dbm": -70.0, "frequency_mhz": 5180,
                     "last_seen_ms": T0 + 150},
                ],
            },
            {
                "t_ms": T0 + 900,
                "aps": [{"bssid": "02:00:00:00:00:03", "rssi_dbm": -80.0, "frequency_mhz": 2412}],
            },
        ],
        bluetooth=[
            {"kind": "peer", "t_ms": T0 + 300, "peer_advertised_id": "ble-2", "rssi_dbm": -72.0},
            {"kind": "beacon", "t_ms": T0 + 400, "mac": "aa:bb:cc:dd:ee:ff", "rssi_dbm": -66.0},
        ],
        anchor_detections=[{"t_ms": T0 + 500, "type": "stairs"}],
    )  # fmt: skip


def _walking() -> UserBatch:
    return convert.sensor_arrays(_walking_batch())


def _raw_imu() -> UserBatch:
    n = 7
    t = [T0 + 5 * i for i in range(n)]
    axis = [0.1 * i for i in range(n)]
    batch = _sensor_batch(
        accelerometer={"t_ms": t, "x": axis, "y": axis, "z": [9.8] * n},
        gyroscope={"t_ms": t, "x": axis, "y": axis, "z": axis},
        rotation_vector={"t_ms": t, "x": [0.0] * n, "y": [0.0] * n, "z": [0.1] * n},  # no w: NaN
        pressure={"t_ms": t[:3], "value": [1000.0, 1000.1, 1000.2]},
    )
    arrays = convert.sensor_arrays(batch)
    assert arrays.imu is not None
    return arrays


def _with_signatures() -> UserBatch:
    return UserBatch(
        user="u",
        fix_t=np.array([T0], dtype=np.int64),
        fix_xy=np.array([[1.0, 2.0]]),
        fix_sigma=np.array([0.5]),
        fix_azimuth=np.array([np.nan]),
        step_t=np.array([T0 + 1], dtype=np.int64),
        step_length=np.array([0.7]),
        step_azimuth=np.array([0.1]),
        step_turn=np.array([np.nan]),
        step_heading_offset=np.array([0.25]),
        detect_t=np.array([T0 + 2, T0 + 3], dtype=np.int64),
        detect_type=np.array([5, 6], dtype=np.int64),
        detect_signature=("beacon:aa", ""),
        detect_observed_t=np.array([T0 + 1, T0 + 3], dtype=np.int64),
    )


CASES = {
    "walking": _walking,
    "raw imu": _raw_imu,
    "signatures": _with_signatures,
    "empty": lambda: UserBatch("u"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_an_unpacked_batch_equals_the_packed_one_in_value_and_type(case: str) -> None:
    original = CASES[case]()
    packed = pickle.loads(pickle.dumps(batch_transport.pack(original), protocol=pickle.HIGHEST_PROTOCOL))
    restored = batch_transport.unpack(packed)
    assert isinstance(restored, UserBatch)
    pairs = [
        (f.name, getattr(original, f.name), getattr(restored, f.name)) for f in dataclasses.fields(UserBatch)
    ]
    if original.imu is not None:
        assert isinstance(restored.imu, ImuSamples)
        pairs += [
            (f"imu.{f.name}", getattr(original.imu, f.name), getattr(restored.imu, f.name))
            for f in dataclasses.fields(ImuSamples)
        ]
    for name, want, got in pairs:
        if isinstance(want, np.ndarray):
            assert got.dtype == want.dtype, name
            assert got.shape == want.shape, name
            assert np.array_equal(got, want, equal_nan=True), name
            assert numba.typeof(got) == numba.typeof(want), name
            assert got.flags.writeable, name
        elif name != "imu":
            assert got == want, name
    assert (restored.imu is None) == (original.imu is None)


def test_unpacked_arrays_do_not_share_memory_with_the_message() -> None:
    """The building may keep a batch's arrays: they must not be views of a buffer the socket reuses."""
    packed = batch_transport.pack(_walking())
    restored = batch_transport.unpack(packed)
    before = bytes(packed.floats)
    restored.step_length[0] = 99.0
    assert packed.floats == before


def test_the_front_converts_every_batch_and_leaves_its_landmarks_to_the_building() -> None:
    fix = {"kind": "fix", "t_ms": T0, "position": {"x_m": 1.0, "y_m": 2.0}, "sigma_m": 1.0}
    steps = [{"t_ms": T0, "length_m": 0.7, "azimuth_rad": 0.0}]
    batch = _sensor_batch(steps=steps, landmarks=[fix])
    submission = Submission.of(batch, b"{}", 0)
    assert submission.header == BatchHeader.of(batch)
    assert submission.landmarks == tuple(batch.landmarks)
    arrays = batch_transport.unpack(submission.columns)
    assert arrays.step_t.tolist() == [T0]
    assert arrays.fix_t.size == 0  # placed by the building, not the front
    assert BatchHeader.of(_sensor_batch()) == ("phone-1", "phone-1", "b-1", 4, None, None, None)


def test_a_batch_crosses_to_its_building_process_as_the_front_converted_it() -> None:
    """``batch_fields`` (the front) and ``received_batch`` (the building), through pickle as on the socket:
    the submission arrives as it left, its landmarks apart for the building to place."""
    steps = [{"t_ms": T0, "length_m": 0.7, "azimuth_rad": 0.0}]
    fix = {"kind": "fix", "t_ms": T0, "position": {"x_m": 1.0, "y_m": 2.0}, "sigma_m": 1.0}
    imu = {"accelerometer": {"t_ms": [T0, T0 + 20], "x": [0.0, 0.1], "y": [0.0, 0.0], "z": [9.8, 9.7]}}
    for extra in ({"steps": steps}, {"steps": steps, "landmarks": [fix]}, {**imu, "landmarks": [fix]}):
        batch = _sensor_batch(**extra)
        raw = batch.model_dump_json().encode()
        sent = Submission.of(batch, raw, 7)
        fields = pickle.loads(pickle.dumps(batch_fields(sent), protocol=5))
        assert received_batch(*fields) == sent


def test_an_earlier_fronts_batch_without_its_columns_is_converted_by_the_building() -> None:
    batch = _sensor_batch(landmarks=[{"kind": "fix", "t_ms": T0, "position": {"x_m": 1.0, "y_m": 2.0}}])
    raw = batch.model_dump_json().encode()
    received = received_batch(raw, 7, tuple(BatchHeader.of(batch)), None)
    assert received == Submission.of(batch, raw, 7)


def _context() -> convert.BuildingContext:
    return convert.BuildingContext(
        "hq",
        GeoFrame(48.0, 11.0, 0.0),
        Extent(-10.0, 60.0, -10.0, 40.0, 10.0),
        frozenset({0, 1}),
        {"door": convert.KnownPlace(3.0, 4.0, 0), "lift": convert.KnownPlace(8.0, 1.0, 1)},
        0.5,
    )


_FIX = {"kind": "fix", "t_ms": T0, "position": {"x_m": 1.0, "y_m": 2.0}}
_LANDMARK_SETS: dict[str, list[dict[str, Any]]] = {
    "a fix on a floor": [{**_FIX, "floor": 1}],
    "anchors, one unknown": [
        {"kind": "anchor", "t_ms": T0, "anchor_id": "lift"},
        {"kind": "anchor", "t_ms": T0 + 5, "anchor_id": "nowhere"},
        {**_FIX, "t_ms": T0 + 9, "sigma_m": 2.0, "azimuth_rad": 1.0},
    ],
    "a GPS fix": [{"kind": "gps", "t_ms": T0, "lat_deg": 48.0001, "lon_deg": 11.0001, "accuracy_m": 4.0}],
    "outside the extent": [{**_FIX, "position": {"x_m": 500.0, "y_m": 2.0}}],
    "on a floor it does not have": [{**_FIX, "floor": 3}],
}


@pytest.mark.parametrize("name", list(_LANDMARK_SETS))
def test_landmarks_placed_by_the_building_give_what_the_whole_batch_gives(name: str) -> None:
    """The oracle: the whole batch converted at once (``sensor_arrays`` and ``landmark_fixes``). The front's
    columns, then ``placed`` in the building, give the same arrays and warnings, or the same refusal."""
    steps = [{"t_ms": T0 + 1, "length_m": 0.7, "azimuth_rad": 0.0}]
    batch = _sensor_batch(steps=steps, landmarks=_LANDMARK_SETS[name])
    ctx = _context()
    received = received_batch(*batch_fields(Submission.of(batch, b"{}", 0)))
    assert received.landmarks
    try:
        fixes, warnings = convert.landmark_fixes(batch.landmarks, ctx)
    except ValueError as exc:
        assert name in ("outside the extent", "on a floor it does not have")
        with pytest.raises(ValueError, match="^" + re.escape(str(exc)) + "$"):
            convert.placed(received.columns, received.landmarks, ctx)
        return
    whole = UserBatch(**{**vars(convert.sensor_arrays(batch)), **fixes})
    assert bool(warnings) == (name == "anchors, one unknown")
    placed = convert.placed(received.columns, received.landmarks, ctx)
    assert placed.warnings == warnings
    assert convert.to_user_batch(batch, ctx).warnings == warnings
    assert placed.user_batch.fix_t.size == whole.fix_t.size > 0
    for f in dataclasses.fields(UserBatch):
        a, b = getattr(placed.user_batch, f.name), getattr(whole, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
        else:
            assert a == b, f.name


@pytest.mark.parametrize("raw_imu", [False, True])
def test_a_batch_the_front_cannot_convert_is_refused_there(
    monkeypatch: pytest.MonkeyPatch, raw_imu: bool
) -> None:
    def refuse(*args: object) -> None:
        raise ValueError("user batch of 'phone-1': inconsistent array shapes")

    monkeypatch.setattr(convert, "sensor_arrays" if raw_imu else "check_values", refuse)
    extra = {"gyroscope": {"t_ms": [T0], "x": [0.0], "y": [0.0], "z": [0.1]}} if raw_imu else {}
    with pytest.raises(InvalidInputError, match="inconsistent array shapes"):
        Submission.of(_sensor_batch(**extra), b"{}", 0)


_MACS = [f"02:00:00:00:00:{i:02x}" for i in range(40)]


@st.composite
def _phone_batches(draw: st.DrawFn) -> SensorBatch:
    """Batches of a phone that counts its own steps: any mix of steps (with a heading, a turn or both), scans
    (cached APs too), peers, beacons and anchor detections."""

    def times(n: int) -> list[int]:
        return sorted(draw(st.lists(st.integers(0, 900), min_size=n, max_size=n, unique=True)))

    n_steps, n_scans, n_bt, n_det = (draw(st.integers(0, 4)) for _ in range(4))
    angle = st.floats(-3.1, 3.1)
    steps = []
    for t in times(n_steps):
        azimuth, turn = draw(st.sampled_from([(True, False), (False, True), (True, True)]))
        steps.append({
            "t_ms": T0 + t, "length_m": draw(st.floats(0.01, 3.0)),
            "azimuth_rad": draw(angle) if azimuth else None,
            "heading_change_rad": draw(angle) if turn else None,
        })  # fmt: skip
    scans = []
    for t in times(n_scans):
        macs = draw(st.lists(st.sampled_from(_MACS), min_size=1, max_size=6, unique=True))
        scans.append({"t_ms": T0 + t, "aps": [
            {"bssid": m, "rssi_dbm": draw(st.floats(-100.0, -20.0)), "frequency_mhz": 2437,
             "last_seen_ms": draw(st.one_of(st.none(), st.integers(T0 - 5_000, T0 + t)))}
            for m in macs
        ]})  # fmt: skip
    bluetooth = [
        {"kind": "peer", "t_ms": T0 + t, "peer_advertised_id": f"ble-{t}", "rssi_dbm": -70.0 - t % 20}
        if draw(st.booleans())
        else {"kind": "beacon", "t_ms": T0 + t, "mac": _MACS[t % 40], "rssi_dbm": -80.0 + t % 7}
        for t in times(n_bt)
    ]
    detections = [
        {"t_ms": T0 + t, "type": draw(st.sampled_from(["stairs", "elevator", "turn"]))} for t in times(n_det)
    ]
    return _sensor_batch(
        ble_advertised_id=draw(st.one_of(st.none(), st.just("ble-me"))),
        steps=steps, wifi_scans=scans, bluetooth=bluetooth, anchor_detections=detections,
    )  # fmt: skip


@settings(max_examples=150, deadline=None)
@given(_phone_batches())
def test_the_front_packs_straight_what_converting_then_packing_gives(batch: SensorBatch) -> None:
    assert convert.packed(batch) == batch_transport.pack(convert.sensor_arrays(batch))


def test_batches_with_raw_imu_are_packed_from_their_arrays() -> None:
    fix = {"kind": "fix", "t_ms": T0, "position": {"x_m": 1.0, "y_m": 2.0}, "sigma_m": 1.0}
    with_fix = _sensor_batch(landmarks=[fix])
    assert convert.packed(with_fix) == batch_transport.pack(convert.sensor_arrays(with_fix))
    raw = _sensor_batch(gyroscope={"t_ms": [T0], "x": [0.0], "y": [0.0], "z": [0.1]})
    assert batch_transport.unpack(convert.packed(raw)).imu is not None
    assert convert.packed(_walking_batch()) == batch_transport.pack(_walking())


def test_a_phone_that_counts_its_steps_still_sends_its_barometer() -> None:
    body = _walking_batch().model_dump() | {"pressure": {"t_ms": [T0, T0 + 200], "value": [1000.0, 999.9]}}
    batch = SensorBatch.model_validate(body)
    ub = convert.sensor_arrays(batch)
    assert ub.step_t.size == 2
    assert ub.imu is not None
    np.testing.assert_array_equal(ub.imu.pressure, [[T0, 1000.0], [T0 + 200, 999.9]])
    assert ub.imu.acc.shape == (0, 4)
    back = batch_transport.unpack(batch_transport.pack(ub))
    assert back.imu is not None
    np.testing.assert_array_equal(back.imu.pressure, ub.imu.pressure)


def test_values_the_engine_refuses_are_refused_when_packed_straight() -> None:
    """The wire model's bounds keep these out; were one to slip in, the front answers as ``UserBatch``."""
    for field, value in (("length_m", math.nan), ("length_m", -0.5)):
        step = {"t_ms": T0, "length_m": 0.7, "azimuth_rad": 0.0}
        batch = _sensor_batch(steps=[step])
        broken = batch.model_copy(update={"steps": [batch.steps[0].model_copy(update={field: value})]})
        with pytest.raises(ValueError, match="non-finite values, sigma <= 0 or negative lengths"):
            convert.packed(broken)
        with pytest.raises(ValueError, match="non-finite values, sigma <= 0 or negative lengths"):
            convert.sensor_arrays(broken)


def test_pack_lists_refuses_unknown_fields() -> None:
    with pytest.raises(ValueError, match="not fields of a packed batch"):
        batch_transport.pack_lists("u", None, {"steps": [1]}, {}, {})
