"""MCAP recordings: every accepted batch (as posted) and every estimate, per building, one file per hour.

Channels use JSON encoding with JSON-schema schemas generated from ``schemas/``: ``/batches``
(``SensorBatch``), ``/estimates`` (``Estimate``) and ``/poses`` (Foxglove's well-known ``PoseInFrame``, so a
recording opens in Foxglove or Lichtblick). Records go in zstd-compressed chunks, written when a chunk is
full (``CHUNK_BYTES``) and at least every ``FLUSH_S`` seconds: a crash loses at most the records of that last
chunk, and a file cut short is still readable up to its last whole chunk. A recording is not the
acknowledgement of a batch: the batch log in SQL is. The building keeps its recordings whole through a crash
all the same: it flushes them before it writes a snapshot (so every batch a snapshot covers is in a file),
and records again the batches it replays from its log when it loads (a batch may then be in a recording
twice, with the same id: readers keep the first).

The files are written by the Foxglove SDK's MCAP writer (compiled: ~3 us a message, where the ``mcap``
package's Python writer took ~9-25 us, three messages a batch); the ``mcap`` package reads them.

Recordings are kept ``CROWDSLAM_RECORDING_DAYS`` and under ``CROWDSLAM_RECORDING_MAX_GB``
(``prune_recordings``): whole files go, oldest first.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

import foxglove
from foxglove.mcap import MCAPCompression, MCAPWriteOptions, MCAPWriter
from mcap.exceptions import McapError
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from schemas.estimates import Estimate
from schemas.sensors import SensorBatch

CHUNK_BYTES = 1 << 20
"""A chunk is compressed and written once it holds this much (a busy building's second or so)."""
FLUSH_S = 5.0
"""...and at least this often, so that a quiet building's crash loses seconds of recording, not an hour."""

BATCH_TOPIC = "/batches"
ESTIMATE_TOPIC = "/estimates"
POSE_TOPIC = "/poses"

POSE_IN_FRAME_SCHEMA: dict[str, Any] = {
    "title": "foxglove.PoseInFrame",
    "description": "A timestamped pose for an object or reference frame in 3D space",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
        },
        "frame_id": {"type": "string"},
        "pose": {
            "type": "object",
            "properties": {
                "position": {
                    "type": "object",
                    "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}},
                },
                "orientation": {
                    "type": "object",
                    "properties": {
                        "x": {"type": "number"},
                        "y": {"type": "number"},
                        "z": {"type": "number"},
                        "w": {"type": "number"},
                    },
                },
            },
        },
    },
}


def pose_in_frame_json(estimate: Estimate) -> bytes:
    """Foxglove ``PoseInFrame`` JSON in the building frame (yaw is the heading, counter-clockwise from east),
    to the millimetre (as ``estimate_json``), formatted directly: a third of the cost of ``json.dumps`` of a
    dict (the numbers are finite, see
    ``server.ingestion.convert.estimate``; the frame id needs no escaping: building and user ids are
    ``Identifier``s, letters, digits and ``._:-``)."""
    half = estimate.heading_rad / 2.0
    position = estimate.position
    t_ms = estimate.t_ms
    return (
        f'{{"timestamp":{{"sec":{t_ms // 1000},"nsec":{(t_ms % 1000) * 1_000_000}}},'
        f'"frame_id":"{estimate.building_id}/{estimate.user_id}","pose":{{"position":{{"x":{_mm(position.x_m)},'
        f'"y":{_mm(position.y_m)},"z":0.0}},"orientation":{{"x":0.0,"y":0.0,'
        f'"z":{round(math.sin(half), 5)!r},"w":{round(math.cos(half), 5)!r}}}}}}}'
    ).encode()


def estimate_json(estimate: Estimate) -> bytes:
    """An ``Estimate`` as recorded: its JSON with positions to the millimetre, covariances to the square
    millimetre, angles to 1e-4 rad and geographic coordinates to ~1 mm, formatted directly. Seventeen
    digits of a position known to a metre are noise that no compression removes: rounded, an estimate
    compresses to half. Identifiers need no escaping (``Identifier``: letters, digits and ``._:-``)."""
    p, c, best = estimate.position, estimate.covariance_m2, estimate.best_particle
    best_json = "null" if best is None else f'{{"x_m":{_mm(best.x_m)},"y_m":{_mm(best.y_m)}}}'
    lat = "null" if estimate.lat_deg is None else repr(round(estimate.lat_deg, 8))
    lon = "null" if estimate.lon_deg is None else repr(round(estimate.lon_deg, 8))
    return (
        f'{{"building_id":"{estimate.building_id}","user_id":"{estimate.user_id}",'
        f'"device_id":"{estimate.device_id}","t_ms":{estimate.t_ms},'
        f'"position":{{"x_m":{_mm(p.x_m)},"y_m":{_mm(p.y_m)}}},'
        f'"covariance_m2":[[{_mm2(c[0][0])},{_mm2(c[0][1])}],[{_mm2(c[1][0])},{_mm2(c[1][1])}]],'
        f'"best_particle":{best_json},"heading_rad":{round(estimate.heading_rad, 4)!r},'
        f'"floor":{estimate.floor},"floor_probability":{round(estimate.floor_probability, 4)!r},'
        f'"source":"{estimate.source.value}","lat_deg":{lat},"lon_deg":{lon}}}'
    ).encode()


def _mm(metres: float) -> str:
    return repr(round(metres, 3))


def _mm2(square_metres: float) -> str:
    return repr(round(square_metres, 6))


class BuildingRecorder:
    """Writes one building's recordings. Used from that building's thread only."""

    def __init__(
        self, root: Path, building_id: str, chunk_bytes: int = CHUNK_BYTES, flush_s: float = FLUSH_S
    ) -> None:
        self._dir = root / building_id
        self._chunk_bytes = chunk_bytes
        self._flush_s = flush_s
        self._hour: str | None = None
        self._file: IO[bytes] | None = None
        self._writer: MCAPWriter | None = None
        self._channels: dict[str, foxglove.Channel] = {}
        self._context: foxglove.Context | None = None
        self._hour_ends_ns = -1
        self._flushed = time.monotonic()
        self.n_batches = 0

    @property
    def root(self) -> Path:
        """The recordings of every building: this one's are in ``root / building_id``."""
        return self._dir.parent

    def _open(self, t_ns: int) -> MCAPWriter:
        if self._writer is not None and t_ns < self._hour_ends_ns:
            return self._writer
        now = datetime.fromtimestamp(t_ns / 1e9, UTC)
        hour = now.strftime("%Y%m%dT%H")
        self._hour_ends_ns = int(now.replace(minute=0, second=0, microsecond=0).timestamp() + 3600) * 10**9
        if self._writer is not None and hour == self._hour:
            return self._writer
        self.close()
        self._dir.mkdir(parents=True, exist_ok=True)
        path = self._dir / f"{hour}.mcap"
        n = 0
        while True:  # a restart within the hour starts a new file beside the old one
            try:  # created exclusively: in a cluster, the worker taking a building over shares the folder
                self._file = path.open("xb")
                break
            except FileExistsError:
                n += 1
                path = self._dir / f"{hour}-{n}.mcap"
        # a file's own context: its channels go to this writer only (kept: a context dropped closes them)
        context = self._context = foxglove.Context()
        writer = foxglove.open_mcap(
            self._file,
            context=context,
            writer_options=MCAPWriteOptions(
                compression=MCAPCompression.Zstd,
                chunk_size=self._chunk_bytes,
                # no message indexes (16 bytes a message, uncompressed, a third of a compressed batch):
                # readers find messages through the chunk index, and a chunk is read whole anyway
                emit_message_indexes=False,
                compression_threads=0,  # on the building's own thread (the SDK would start one a core)
                profile="",
            ),
        )
        schemas = {
            BATCH_TOPIC: ("SensorBatch", SensorBatch.model_json_schema()),
            ESTIMATE_TOPIC: ("Estimate", Estimate.model_json_schema()),
            POSE_TOPIC: ("foxglove.PoseInFrame", POSE_IN_FRAME_SCHEMA),
        }
        self._channels = {
            topic: foxglove.Channel(
                topic,
                schema=foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode()),
                message_encoding="json",
                context=context,
            )
            for topic, (name, schema) in schemas.items()
        }
        self._writer, self._hour = writer, hour
        return writer

    def record_batch(self, raw: bytes, received_ns: int) -> None:
        """Append a batch as posted."""
        self._open(received_ns)
        self._channels[BATCH_TOPIC].log(raw, log_time=received_ns)
        self.n_batches += 1

    def record_estimates(self, estimates: list[Estimate], received_ns: int) -> None:
        if not estimates:
            return
        self._open(received_ns)
        estimate_channel, pose_channel = self._channels[ESTIMATE_TOPIC], self._channels[POSE_TOPIC]
        for e in estimates:
            t = e.t_ms * 1_000_000
            estimate_channel.log(estimate_json(e), log_time=t)
            pose_channel.log(pose_in_frame_json(e), log_time=t)

    def flush(self, now: bool = False) -> None:
        """Called once per group, and by a quiet building: the chunk in progress is compressed and written
        once ``FLUSH_S`` have passed since the last (a full chunk is written as it fills), or ``now``."""
        if self._writer is not None and (now or time.monotonic() - self._flushed >= self._flush_s):
            self._writer.flush()
            if self._file is not None:  # out of this process: a crash of it loses nothing flushed
                self._file.flush()
            self._flushed = time.monotonic()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
            self._channels, self._context = {}, None
        if self._file is not None:
            self._file.close()
            self._file = None


@dataclass(frozen=True)
class RecordedBatch:
    received_ns: int
    raw: bytes


def read_batches(path: Path) -> Iterator[RecordedBatch]:
    """The batches of a recording in recorded order; a file cut short (a crash) ends at its last whole
    record."""
    with path.open("rb") as stream:
        batch_channels: set[int] = set()
        try:
            for record in StreamReader(stream, skip_magic=False).records:
                if isinstance(record, Channel) and record.topic == BATCH_TOPIC:
                    batch_channels.add(record.id)
                elif isinstance(record, Message) and record.channel_id in batch_channels:
                    yield RecordedBatch(record.log_time, bytes(record.data))
        except (McapError, EOFError):
            return


@dataclass(frozen=True)
class Pruned:
    files: int
    bytes: int


RECENT_S = 3600.0
"""A recording written to in the last hour is never deleted: it may be one a building is writing."""


def prune_recordings(root: Path, max_age_s: float | None, max_bytes: int | None, now: float) -> Pruned:
    """Delete whole recordings under ``root`` (every building's ``*.mcap``): those last written more than
    ``max_age_s`` before ``now`` (Unix seconds), then, oldest first, as many as it takes to bring them all
    under ``max_bytes``. Age is the file's last write, not the hour in its name: a replay or an import
    records batches received long ago into files written now. A file written to in the last ``RECENT_S``
    is never deleted (any building may be writing it), nor counted. A file another process deleted first
    is passed over."""
    files = []
    for path in root.glob("*/*.mcap"):
        try:
            stat = path.stat()
        except FileNotFoundError:
            continue
        if now - stat.st_mtime >= RECENT_S:
            files.append((stat.st_mtime, str(path), path, stat.st_size))
    files.sort()
    total = sum(size for *_, size in files) if max_bytes is not None else 0
    deleted = freed = 0
    for written, _, path, size in files:
        too_old = max_age_s is not None and now - written > max_age_s
        too_much = max_bytes is not None and total > max_bytes
        if not (too_old or too_much):
            break  # oldest first: the rest are younger, and the total fits
        try:
            path.unlink()
        except FileNotFoundError:
            pass
        else:
            deleted += 1
            freed += size
        total -= size
    return Pruned(deleted, freed)
