"""The sensor batch a phone posts: any mix of raw IMU streams, client-side steps, radio scans and landmarks.

A batch covers a short span of time (typically one second, at most ``MAX_BATCH_SPAN_MS``). A batch with
only IMU, or only steps, is normal: iPhones send no WiFi scans and Android throttles them to 4 per 2 min.

IMU streams are columnar (one list per axis) so a second at 200 Hz is a few short arrays, not hundreds of
objects. Axes and units follow Android's ``SensorEvent`` semantics in the phone's own frame.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal, Self

from pydantic import Field, model_validator

from schemas.anchors import AnchorType
from schemas.common import (
    MAX_TIME_MS,
    MIN_TIME_MS,
    Identifier,
    IncreasingTimes,
    Position,
    RssiDbm,
    TimeMs,
    TxPowerDbm,
    WireModel,
    wire_config,
)

MAX_BATCH_SPAN_MS = 60_000
"""A batch spans at most one minute of sensor time."""
MAX_IMU_SAMPLES = 12_000
"""Per stream: one minute at 200 Hz."""
MAX_STEPS = 300
MAX_WIFI_SCANS = 60
MAX_APS_PER_SCAN = 1024
"""Scans in dense buildings list over 500 APs (the msindoor mall: up to 522, mostly cached entries)."""
MAX_BLUETOOTH_SIGHTINGS = 3_000
MAX_LANDMARKS = 100
MAX_LTE_MEASUREMENTS = 300
MIN_PRESSURE_HPA, MAX_PRESSURE_HPA = 300.0, 1100.0
"""Air pressure from the top of Everest to below the Dead Sea, with margin."""
MAX_BATCH_BYTES = 2 * 1024 * 1024
"""Largest accepted request body (bytes); larger bodies are refused with 413 before parsing."""


MAX_SENSOR_VALUE = 10_000.0
"""Any IMU axis's magnitude: above every phone sensor's range (accelerometers +-160 m/s^2, gyroscopes +-35
rad/s, magnetometers +-5,000 uT), far below what could overflow the dead reckoning."""
SensorValues = Annotated[
    list[Annotated[float, Field(ge=-MAX_SENSOR_VALUE, le=MAX_SENSOR_VALUE)]],
    Field(max_length=MAX_IMU_SAMPLES),
]


class _Stream(WireModel):
    t_ms: IncreasingTimes = Field(
        max_length=MAX_IMU_SAMPLES, description="Sample times, strictly increasing."
    )

    def _check_columns(self, **columns: list[float] | None) -> None:
        n = len(self.t_ms)
        for name, values in columns.items():
            if values is not None and len(values) != n:
                raise ValueError(f"column '{name}' has {len(values)} values but t_ms has {n}")


class Vector3Stream(_Stream):
    """Three-axis samples in the phone frame (Android ``SensorEvent.values[0..2]``)."""

    x: SensorValues
    y: SensorValues
    z: SensorValues

    @model_validator(mode="after")
    def _columns(self) -> Self:
        self._check_columns(x=self.x, y=self.y, z=self.z)
        return self


class RotationVectorStream(_Stream):
    """Android rotation vector: the unit quaternion's vector part (x, y, z = axis * sin(angle/2)) and,
    when the phone sends it, its scalar part w = cos(angle/2). Without ``w`` it is reconstructed."""

    x: list[float] = Field(max_length=MAX_IMU_SAMPLES)
    y: list[float] = Field(max_length=MAX_IMU_SAMPLES)
    z: list[float] = Field(max_length=MAX_IMU_SAMPLES)
    w: list[float] | None = Field(default=None, max_length=MAX_IMU_SAMPLES)

    @model_validator(mode="after")
    def _columns(self) -> Self:
        self._check_columns(x=self.x, y=self.y, z=self.z, w=self.w)
        for i, (a, b, c) in enumerate(zip(self.x, self.y, self.z, strict=True)):
            norm2 = a * a + b * b + c * c + (self.w[i] ** 2 if self.w is not None else 0.0)
            if norm2 > 1.0 + 1e-3:
                raise ValueError(
                    f"rotation vector sample {i} has norm {norm2**0.5:.4f} > 1; not a unit quaternion"
                )
        return self


class ScalarStream(_Stream):
    """One value per sample (pressure in hPa)."""

    value: list[float] = Field(max_length=MAX_IMU_SAMPLES)

    @model_validator(mode="after")
    def _columns(self) -> Self:
        self._check_columns(value=self.value)
        return self


class Step(WireModel):
    """A step detected on the phone. Give the absolute azimuth, the heading change, or both."""

    t_ms: TimeMs
    length_m: float = Field(gt=0.0, le=3.0, description="Step length in metres.")
    azimuth_rad: float | None = Field(
        default=None,
        ge=-7.0,
        le=7.0,
        description="Direction of travel, clockwise from north (Android getOrientation()[0] convention).",
    )
    heading_change_rad: float | None = Field(
        default=None,
        ge=-7.0,
        le=7.0,
        description="Change of direction since the previous step, counter-clockwise positive.",
    )

    @model_validator(mode="after")
    def _has_direction(self) -> Self:
        if self.azimuth_rad is None and self.heading_change_rad is None:
            raise ValueError("a step needs azimuth_rad, heading_change_rad or both")
        return self


class WifiAp(WireModel):
    bssid: str = Field(pattern=r"^[0-9a-fA-F]{2}(:[0-9a-fA-F]{2}){5}$", examples=["0e:74:9c:a7:b2:e4"])
    ssid: str = Field(default="", max_length=64)
    rssi_dbm: RssiDbm
    frequency_mhz: int = Field(ge=2400, le=7125)
    last_seen_ms: TimeMs | None = Field(
        default=None,
        description="When the AP was last actually heard (Android ScanResult.timestamp as wall clock). "
        "Scans re-report cached APs; entries older than the scan are down-weighted or dropped.",
    )


class WifiScan(WireModel):
    t_ms: TimeMs
    aps: list[WifiAp] = Field(min_length=1, max_length=MAX_APS_PER_SCAN)

    @model_validator(mode="after")
    def _unique_and_causal(self) -> Self:
        seen: set[str] = set()
        for ap in self.aps:
            key = ap.bssid.lower()
            if key in seen:
                raise ValueError(f"BSSID {ap.bssid} appears twice in one scan")
            seen.add(key)
            if ap.last_seen_ms is not None and ap.last_seen_ms > self.t_ms + 1_000:
                raise ValueError(f"AP {ap.bssid} last_seen_ms is after the scan time t_ms")
        return self


class PeerSighting(WireModel):
    """Another phone running the app, heard over Bluetooth LE by its advertised id."""

    kind: Literal["peer"] = "peer"
    t_ms: TimeMs
    peer_advertised_id: Identifier
    rssi_dbm: RssiDbm
    tx_power_dbm: TxPowerDbm | None = None


class BeaconSighting(WireModel):
    """A fixed Bluetooth beacon; identified by MAC (uuid/major/minor repeat across beacons in practice)."""

    kind: Literal["beacon"] = "beacon"
    t_ms: TimeMs
    mac: str = Field(pattern=r"^[0-9a-fA-F]{2}(:[0-9a-fA-F]{2}){5}$")
    uuid: str | None = Field(default=None, max_length=36)
    major: int | None = Field(default=None, ge=0, le=65535)
    minor: int | None = Field(default=None, ge=0, le=65535)
    rssi_dbm: RssiDbm
    tx_power_dbm: TxPowerDbm | None = None


BluetoothSighting = Annotated[PeerSighting | BeaconSighting, Field(discriminator="kind")]


class GpsFix(WireModel):
    kind: Literal["gps"] = "gps"
    t_ms: TimeMs
    lat_deg: float = Field(ge=-90.0, le=90.0)
    lon_deg: float = Field(ge=-180.0, le=180.0)
    accuracy_m: float = Field(gt=0.0, le=500.0)


_TAG_POSITION = re.compile(
    r"^#(?P<id>\S+)\s+(?P<lat>[-+]?\d+(?:\.\d+)?),\s*(?P<lon>[-+]?\d+(?:\.\d+)?)(?:\s+z(?P<z>[-+]?\d+))?\s*$"
)


class TagReading(WireModel):
    """A QR code or NFC tag. ``payload`` may encode its own position as in SignalSLAM, e.g.
    ``#6e1ebc 40.684492,-74.401406 z0`` (id, latitude, longitude, floor); a payload starting with ``#`` must
    follow that form."""

    kind: Literal["tag"] = "tag"
    t_ms: TimeMs
    tag_id: Identifier
    payload: str | None = Field(default=None, max_length=256, examples=["#6e1ebc 40.684492,-74.401406 z0"])

    @model_validator(mode="after")
    def _encoded_position(self) -> Self:
        if self.payload is not None and self.payload.startswith("#"):
            self.encoded_position()  # raises with a clear message when malformed
        return self

    def encoded_position(self) -> tuple[float, float, int] | None:
        """(latitude, longitude, floor) encoded in the payload, or None when it encodes none."""
        if self.payload is None or not self.payload.startswith("#"):
            return None
        match = _TAG_POSITION.match(self.payload)
        if match is None:
            raise ValueError(
                "a tag payload starting with '#' must read '#<id> <lat>,<lon> [z<floor>]', "
                f"e.g. '#6e1ebc 40.684492,-74.401406 z0'; got {self.payload!r}"
            )
        lat, lon = float(match["lat"]), float(match["lon"])
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            raise ValueError(f"tag position {lat},{lon} is outside the WGS-84 range")
        return lat, lon, int(match["z"] or 0)


class AnchorReading(WireModel):
    """The user confirmed being at an operator-known anchor (by its id)."""

    kind: Literal["anchor"] = "anchor"
    t_ms: TimeMs
    anchor_id: Identifier


class PositionFix(WireModel):
    """A position in the building's local frame known from outside the filter: an entrance kiosk, an
    operator's app, a surveyor click. A user's first fix (or tag with a position, or known-anchor reading)
    starts its tracking; later fixes re-centre it."""

    kind: Literal["fix"] = "fix"
    t_ms: TimeMs
    position: Position
    sigma_m: float = Field(default=0.5, gt=0.0, le=100.0, description="Per-axis standard deviation (m).")
    azimuth_rad: float | None = Field(
        default=None,
        ge=-7.0,
        le=7.0,
        description="Direction the user faces, clockwise from north; needed when steps carry only turns.",
    )
    floor: int = Field(default=0, ge=-20, le=200)


Landmark = Annotated[GpsFix | TagReading | AnchorReading | PositionFix, Field(discriminator="kind")]


class AnchorDetection(WireModel):
    """A building anchor detected on the phone (an SDK with its own detectors), typed as DynamicSLAM's
    building anchors are; the server associates it with the crowd map. Phones that send raw sensors instead
    leave this empty and the server's detectors do the work."""

    t_ms: TimeMs
    type: AnchorType
    rise_m: float | None = Field(
        default=None,
        ge=-500.0,
        le=500.0,
        description=(
            "For a change of floor (elevator, stairs, escalator): the height gained, up positive, as the "
            "phone's barometer measured it; the server then moves the user to the floor that rise reaches."
        ),
    )


class LteMeasurement(WireModel):
    t_ms: TimeMs
    cell_id: Identifier = Field(description="E-UTRAN cell identity (ECI) or PCI/EARFCN pair, as a string.")
    rsrp_dbm: float = Field(ge=-140.0, le=-44.0)
    rsrq_db: float | None = Field(default=None, ge=-34.0, le=3.0)


BATCH_EXAMPLE: dict[str, Any] = {
    "building_id": "hq",
    "device_id": "phone-1",
    "batch_id": "phone-1-000042",
    "seq": 42,
    "ble_advertised_id": "a1b2c3d4",
    "accelerometer": {
        "t_ms": [1796559880000, 1796559880020, 1796559880040],
        "x": [0.12, 0.10, 0.15],
        "y": [0.31, 0.29, 0.35],
        "z": [9.79, 9.85, 9.72],
    },
    "gyroscope": {
        "t_ms": [1796559880000, 1796559880020, 1796559880040],
        "x": [0.01, 0.00, -0.01],
        "y": [0.00, 0.02, 0.01],
        "z": [0.05, 0.04, 0.06],
    },
    "rotation_vector": {
        "t_ms": [1796559880000, 1796559880020, 1796559880040],
        "x": [0.01, 0.01, 0.01],
        "y": [0.02, 0.02, 0.02],
        "z": [0.38, 0.38, 0.39],
    },
    "steps": [{"t_ms": 1796559880500, "length_m": 0.68, "azimuth_rad": 0.79}],
    "wifi_scans": [
        {
            "t_ms": 1796559880900,
            "aps": [
                {
                    "bssid": "0e:74:9c:a7:b2:e4",
                    "ssid": "lobby",
                    "rssi_dbm": -43,
                    "frequency_mhz": 5805,
                    "last_seen_ms": 1796559880850,
                },
                {"bssid": "04:33:89:79:fc:7c", "rssi_dbm": -70, "frequency_mhz": 2412},
            ],
        }
    ],
    "bluetooth": [
        {"kind": "peer", "t_ms": 1796559880300, "peer_advertised_id": "e5f6a7b8", "rssi_dbm": -71},
        {
            "kind": "beacon",
            "t_ms": 1796559880400,
            "mac": "E0:78:A3:3D:B5:D6",
            "rssi_dbm": -82,
            "tx_power_dbm": -56,
        },
    ],
    "landmarks": [
        {
            "kind": "tag",
            "t_ms": 1796559880700,
            "tag_id": "6e1ebc",
            "payload": "#6e1ebc 40.684492,-74.401406 z0",
        },
        {
            "kind": "fix",
            "t_ms": 1796559880800,
            "position": {"x_m": 12.5, "y_m": 4.0},
            "sigma_m": 1.0,
            "azimuth_rad": 1.57,
        },
    ],
    "lte": [{"t_ms": 1796559880600, "cell_id": "310-410-12345", "rsrp_dbm": -95.5, "rsrq_db": -11.0}],
}


class SensorBatch(WireModel):
    """What a phone posts, about once a second. ``(device_id, batch_id)`` is unique: a retried batch is
    recognised and not applied twice. ``seq`` increases by one per batch of a device and orders them, within
    its install (``install_ms``)."""

    model_config = wire_config(BATCH_EXAMPLE)

    building_id: Identifier
    device_id: Identifier
    user_id: Identifier | None = Field(default=None, description="Defaults to the device id.")
    batch_id: Identifier = Field(description="Client-unique id of this batch; reuse it when retrying.")
    seq: int = Field(ge=0, le=2**62, description="Per-device sequence number, +1 per batch.")
    install_ms: TimeMs | None = Field(
        default=None,
        description="When the app was installed (or its data cleared) on this phone. A batch with a later "
        "install_ms than the device's last starts its seq anew (a reinstalled phone may start at 0 again); "
        "a batch of an earlier install is late. Keep batch_id unique across installs (e.g. prefix it with "
        "install_ms).",
    )
    ble_advertised_id: Identifier | None = Field(
        default=None,
        description="This phone's own Bluetooth LE advertised id, so peers' sightings can be matched.",
    )
    accelerometer: Vector3Stream | None = Field(default=None, description="m/s^2, gravity included.")
    gyroscope: Vector3Stream | None = Field(default=None, description="rad/s, calibrated.")
    magnetometer: Vector3Stream | None = Field(default=None, description="microtesla, calibrated.")
    rotation_vector: RotationVectorStream | None = None
    game_rotation_vector: RotationVectorStream | None = None
    pressure: ScalarStream | None = Field(default=None, description="hPa.")
    steps: list[Step] = Field(default_factory=list, max_length=MAX_STEPS)
    wifi_scans: list[WifiScan] = Field(default_factory=list, max_length=MAX_WIFI_SCANS)
    bluetooth: list[BluetoothSighting] = Field(default_factory=list, max_length=MAX_BLUETOOTH_SIGHTINGS)
    landmarks: list[Landmark] = Field(default_factory=list, max_length=MAX_LANDMARKS)
    anchor_detections: list[AnchorDetection] = Field(default_factory=list, max_length=MAX_LANDMARKS)
    lte: list[LteMeasurement] = Field(default_factory=list, max_length=MAX_LTE_MEASUREMENTS)

    @property
    def effective_user_id(self) -> str:
        return self.user_id or self.device_id

    def time_span_ms(self) -> tuple[int, int] | None:
        """First and last sensor time in the batch, or None for an empty batch."""
        times: list[int] = []
        for stream in (
            self.accelerometer,
            self.gyroscope,
            self.magnetometer,
            self.rotation_vector,
            self.game_rotation_vector,
            self.pressure,
        ):
            if stream is not None and stream.t_ms:
                times += (stream.t_ms[0], stream.t_ms[-1])
        for items in (
            self.steps,
            self.wifi_scans,
            self.bluetooth,
            self.landmarks,
            self.anchor_detections,
            self.lte,
        ):
            times += [item.t_ms for item in items]
        return (min(times), max(times)) if times else None

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        for name in ("steps", "wifi_scans", "anchor_detections"):
            items = getattr(self, name)
            for i in range(1, len(items)):
                if items[i].t_ms <= items[i - 1].t_ms:
                    raise ValueError(f"{name}[{i}].t_ms must be after {name}[{i - 1}].t_ms")
        if self.pressure is not None:
            for i, hpa in enumerate(self.pressure.value):
                if not MIN_PRESSURE_HPA <= hpa <= MAX_PRESSURE_HPA:
                    raise ValueError(
                        f"pressure.value[{i}] = {hpa} hPa is not an air pressure "
                        f"({MIN_PRESSURE_HPA:g}-{MAX_PRESSURE_HPA:g} hPa)"
                    )
        span = self.time_span_ms()
        if span is not None and span[1] - span[0] > MAX_BATCH_SPAN_MS:
            raise ValueError(
                f"batch spans {span[1] - span[0]} ms of sensor time; at most {MAX_BATCH_SPAN_MS} ms per batch"
            )
        return self


__all__ = [
    "MAX_BATCH_BYTES",
    "MAX_TIME_MS",
    "MIN_TIME_MS",
    "AnchorDetection",
    "AnchorReading",
    "BeaconSighting",
    "BluetoothSighting",
    "GpsFix",
    "Landmark",
    "LteMeasurement",
    "PeerSighting",
    "PositionFix",
    "RotationVectorStream",
    "ScalarStream",
    "SensorBatch",
    "Step",
    "TagReading",
    "Vector3Stream",
    "WifiAp",
    "WifiScan",
]
