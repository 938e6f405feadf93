"""MCAP recordings: every accepted batch (as posted) and every estimate, per building, one file per hour.

Channels use JSON encoding with JSON-schema schemas generated from ``schemas/``: ``/batches``
(``SensorBatch``), ``/estimates`` (``Estimate``) and ``/poses`` (Foxglove's well-known ``PoseInFrame``, so a
recording opens in Foxglove or Lichtblick). Chunking is off and the building flushes its file after each
group of batches, before their receipts are sent, so a crash loses no acknowledged batch: a file cut short
is still readable up to its last complete record.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import McapError
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from schemas.estimates import Estimate
from schemas.sensors import SensorBatch

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
    formatted directly: a third of the cost of ``json.dumps`` of a dict (the numbers are finite, see
    ``server.ingestion.convert.estimate``; the frame id needs no escaping: building and user ids are
    ``Identifier``s, letters, digits and ``._:-``)."""
    half = estimate.heading_rad / 2.0
    position = estimate.position
    t_ms = estimate.t_ms
    return (
        f'{{"timestamp":{{"sec":{t_ms // 1000},"nsec":{(t_ms % 1000) * 1_000_000}}},'
        f'"frame_id":"{estimate.building_id}/{estimate.user_id}","pose":{{"position":{{"x":{position.x_m!r},'
        f'"y":{position.y_m!r},"z":0.0}},"orientation":{{"x":0.0,"y":0.0,'
        f'"z":{math.sin(half)!r},"w":{math.cos(half)!r}}}}}}}'
    ).encode()


class BuildingRecorder:
    """Writes one building's recordings. Used from that building's worker thread only."""

    def __init__(self, root: Path, building_id: str) -> None:
        self._dir = root / building_id
        self._hour: str | None = None
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._channels: dict[str, int] = {}
        self._hour_ends_ns = -1
        self.n_batches = 0

    def _open(self, t_ns: int) -> Writer:
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
        writer = Writer(self._file, use_chunking=False)
        writer.start(profile="", library="crowdslam")
        schemas = {
            BATCH_TOPIC: ("SensorBatch", SensorBatch.model_json_schema()),
            ESTIMATE_TOPIC: ("Estimate", Estimate.model_json_schema()),
            POSE_TOPIC: ("foxglove.PoseInFrame", POSE_IN_FRAME_SCHEMA),
        }
        self._channels = {}
        for topic, (name, schema) in schemas.items():
            schema_id = writer.register_schema(
                name=name, encoding="jsonschema", data=json.dumps(schema).encode()
            )
            self._channels[topic] = writer.register_channel(
                topic=topic, message_encoding="json", schema_id=schema_id
            )
        self._writer, self._hour = writer, hour
        return writer

    def record_batch(self, raw: bytes, received_ns: int) -> None:
        """Append a batch as posted (``flush`` before acknowledging it)."""
        writer = self._open(received_ns)
        writer.add_message(
            self._channels[BATCH_TOPIC], log_time=received_ns, data=raw, publish_time=received_ns
        )
        self.n_batches += 1

    def record_estimates(self, estimates: list[Estimate], received_ns: int) -> None:
        if not estimates:
            return
        writer = self._open(received_ns)
        for e in estimates:
            t = e.t_ms * 1_000_000
            writer.add_message(
                self._channels[ESTIMATE_TOPIC],
                log_time=t,
                data=e.model_dump_json().encode(),
                publish_time=received_ns,
            )
            pose = pose_in_frame_json(e)
            writer.add_message(self._channels[POSE_TOPIC], log_time=t, data=pose, publish_time=received_ns)

    def flush(self) -> None:
        """Everything recorded so far reaches the operating system (once per group, before its receipts)."""
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.finish()  # type: ignore[no-untyped-call]
            self._writer = None
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
