"""A converted batch (``UserBatch``) in a compact form for the socket to a building's process.

The front of a building process validates every batch anyway; converting it there too
(``server.ingestion.convert``) takes the re-validation and the conversion off the building's core, the one a
busy building is short of (``bench/building.py --path both`` measures it). Pickled as it is, a ``UserBatch``
is ~25 small arrays that unpickle one by
one more slowly than the JSON decodes, so it travels as one buffer of its integers, one of its floats, their
lengths, and its strings; the building cuts the buffers back into arrays (views of one aligned, writable copy:
the numba kernels see the types a conversion gives them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from slam_core.sensing.pdr.online import ImuSamples
from slam_core.tracking.tracker import UserBatch

_INTS = (
    "fix_t", "step_t", "detect_t", "detect_type", "scan_t", "scan_offsets", "scan_last_seen", "peer_t",
    "beacon_t", "detect_observed_t", "fix_level",
)  # fmt: skip
_FLOATS = (
    "fix_xy", "fix_sigma", "fix_azimuth", "step_length", "step_azimuth", "step_turn", "step_heading_offset",
    "scan_rss", "peer_rss", "beacon_rss", "detect_rise",
)  # fmt: skip
_STRINGS = ("scan_bssid", "peer_id", "beacon_mac", "detect_signature")
_IMU = ("acc", "gyr", "mag", "rv", "grv", "pressure")
_WIDTH = {"fix_xy": 2, "acc": 4, "gyr": 4, "mag": 4, "rv": 5, "grv": 5, "pressure": 2}

_OTHERS = {"user", "ble_id", "imu"}
if {f.name for f in dataclasses.fields(UserBatch)} != {*_INTS, *_FLOATS, *_STRINGS, *_OTHERS}:
    raise ImportError("batch_transport does not carry every field of UserBatch: list the new ones here")
if tuple(f.name for f in dataclasses.fields(ImuSamples)) != _IMU:
    raise ImportError("batch_transport does not carry every stream of ImuSamples: list the new ones here")


class PackedBatch(NamedTuple):
    user: str
    ble_id: str | None
    ints: bytes
    """The integer fields' values, in ``_INTS`` order, as int64."""
    floats: bytes
    """The float fields' values, in ``_FLOATS`` order, then the IMU streams', as float64."""
    int_sizes: tuple[int, ...]
    float_rows: tuple[int, ...]
    imu_rows: tuple[int, ...] | None
    """Rows of each IMU stream, None for a batch without raw IMU."""
    strings: tuple[tuple[str, ...], ...]


def pack(batch: UserBatch) -> PackedBatch:
    int_arrays = [getattr(batch, name) for name in _INTS]
    float_arrays = [getattr(batch, name) for name in _FLOATS]
    imu_rows: tuple[int, ...] | None = None
    if batch.imu is not None:
        streams = [getattr(batch.imu, name) for name in _IMU]
        float_arrays += streams
        imu_rows = tuple(s.shape[0] for s in streams)
    return PackedBatch(
        batch.user,
        batch.ble_id,
        _joined(int_arrays, np.int64),
        _joined(float_arrays, np.float64),
        tuple(a.size for a in int_arrays),
        tuple(a.shape[0] for a in float_arrays[: len(_FLOATS)]),
        imu_rows,
        tuple(getattr(batch, name) for name in _STRINGS),
    )


def pack_lists(
    user: str,
    ble_id: str | None,
    ints: Mapping[str, list[int]],
    floats: Mapping[str, list[float]],
    strings: Mapping[str, tuple[str, ...]],
) -> PackedBatch:
    """``pack`` of a batch without raw IMU given as lists by field name (a field not named is empty; a field
    of rows, such as ``fix_xy``, flat), for a front that reads them straight off the wire model
    (``server.ingestion.convert.packed_without_context``)."""
    unknown = set(ints) - set(_INTS) | set(floats) - set(_FLOATS) | set(strings) - set(_STRINGS)
    if unknown:
        raise ValueError(f"not fields of a packed batch: {sorted(unknown)}")
    int_values: list[int] = []
    for name in _INTS:
        int_values += ints.get(name, ())
    float_values: list[float] = []
    for name in _FLOATS:
        float_values += floats.get(name, ())
    return PackedBatch(
        user,
        ble_id,
        np.array(int_values, dtype=np.int64).tobytes(),
        np.array(float_values, dtype=np.float64).tobytes(),
        tuple(len(ints.get(name, ())) for name in _INTS),
        tuple(len(floats.get(name, ())) // _WIDTH.get(name, 1) for name in _FLOATS),
        None,
        tuple(strings.get(name, ()) for name in _STRINGS),
    )


def unpack(packed: PackedBatch) -> UserBatch:
    """The batch ``pack`` was given, equal field by field. Its checks (``UserBatch.__post_init__``) ran
    when it was converted in the front and are not run again."""
    fields: dict[str, object] = {"user": packed.user, "ble_id": packed.ble_id}
    ints = np.frombuffer(packed.ints, dtype=np.int64).copy()
    _cut(fields, _INTS, packed.int_sizes, ints, 0, _NO_INTS)
    floats = np.frombuffer(packed.floats, dtype=np.float64).copy()
    at = _cut(fields, _FLOATS, packed.float_rows, floats, 0, _NO_FLOATS)
    if packed.imu_rows is None:
        fields["imu"] = None
    else:
        streams: dict[str, object] = {}
        _cut(streams, _IMU, packed.imu_rows, floats, at, _NO_FLOATS)
        imu = ImuSamples.__new__(ImuSamples)
        imu.__dict__.update(streams)
        fields["imu"] = imu
    fields.update(zip(_STRINGS, packed.strings, strict=True))
    batch = UserBatch.__new__(UserBatch)
    batch.__dict__.update(fields)  # a frozen dataclass: filled as its unpickling would
    return batch


# Most of a batch's fields are empty (no fix, no detection, no beacon): one shared empty array each (by row
# width), as the conversion does (``server.ingestion.convert``), rather than one sliced out per field.
# Nothing can be written into an empty array.
_NO_INTS = {1: np.zeros(0, dtype=np.int64)}
_NO_FLOATS = {width: np.zeros((0, width)) if width > 1 else np.zeros(0) for width in (1, 2, 4, 5)}


def _joined(arrays: list[np.ndarray], dtype: type) -> bytes:
    non_empty = [a.ravel() for a in arrays if a.size]
    if not non_empty:
        return b""
    return np.concatenate(non_empty).astype(dtype, copy=False).tobytes()


def _cut(
    into: dict[str, object],
    names: tuple[str, ...],
    rows: tuple[int, ...],
    values: np.ndarray,
    at: int,
    empty: dict[int, np.ndarray],
) -> int:
    """Cut ``names`` (``rows[i]`` rows each) from ``values`` at ``at`` into ``into``, an empty one as
    ``empty[its width]``; where they end."""
    for name, n in zip(names, rows, strict=True):
        width = _WIDTH.get(name, 1)
        if not n:
            into[name] = empty[width]
        elif width == 1:
            into[name] = values[at : at + n]
            at += n
        else:
            into[name] = values[at : at + n * width].reshape(n, width)
            at += n * width
    return at
