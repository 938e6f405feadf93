"""The Foxglove live server beside the API: a building's positions, anchors and encounters on Foxglove's
well-known schemas, checked by recording the server's channels to MCAP and by a Foxglove WebSocket client's
view of the advertised channels."""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from pathlib import Path

import foxglove
import pytest
import websockets
from fastapi.testclient import TestClient
from mcap.reader import make_reader

from server.app import create_app
from server.live.broadcast import Broadcaster
from server.live.foxglove import FoxgloveLive
from server.settings import Settings
from tests.server.api.test_api import _batch
from tests.server.conftest import migrate_with_operator


def _advertised(port: int) -> set[str]:
    async def read() -> set[str]:
        url = f"ws://127.0.0.1:{port}"
        async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:  # type: ignore[list-item]
            topics: set[str] = set()
            for _ in range(5):
                try:
                    frame = await asyncio.wait_for(ws.recv(), timeout=2.0)
                except TimeoutError:
                    break
                if isinstance(frame, str) and (message := json.loads(frame)).get("op") == "advertise":
                    topics |= {c["topic"] for c in message["channels"]}
            return topics

    return asyncio.run(read())


def test_a_building_is_watchable_in_foxglove(sqlite_url: str, tmp_path: Path) -> None:
    operator = migrate_with_operator(sqlite_url)
    settings = Settings(data_dir=tmp_path / "data", database_url=sqlite_url, foxglove_port=0)
    recording = tmp_path / "foxglove.mcap"
    with TestClient(create_app(settings)) as client:
        live = client.app.state.crowdslam.foxglove  # type: ignore[attr-defined]
        assert isinstance(live, FoxgloveLive)
        assert live.port > 0
        op = {"Authorization": f"Bearer {operator}"}
        assert client.post("/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=op).status_code == 201
        anchor = {"type": "elevator", "floor": 0, "position": {"x_m": 12.0, "y_m": 5.0}, "label": "lift"}
        with foxglove.open_mcap(recording, context=live.context):
            assert client.put("/v1/buildings/hq/anchors/lift", json=anchor, headers=op).status_code in (
                200,
                201,
            )
            key = client.post(
                "/v1/buildings/hq/keys", json={"scope": "device", "device_id": "phone-1"}, headers=op
            )
            device = {"Authorization": f"Bearer {key.json()['key']}"}
            for seq in range(3):
                assert (
                    client.post("/v1/buildings/hq/batches", json=_batch(seq), headers=device).status_code
                    == 200
                )
            topics = _advertised(live.port)
        assert {"/buildings/hq/users", "/buildings/hq/poses", "/buildings/hq/anchors"} <= topics
    with recording.open("rb") as f:
        reader = make_reader(f)
        schemas = {c.topic: reader.get_summary().schemas[c.schema_id].name
                   for c in reader.get_summary().channels.values()}  # fmt: skip
        counts = Counter(channel.topic for _, channel, _ in reader.iter_messages())
    assert schemas["/buildings/hq/users"] == "foxglove.SceneUpdate"
    assert schemas["/buildings/hq/poses"] == "foxglove.PosesInFrame"
    assert schemas["/buildings/hq/anchors"] == "foxglove.SceneUpdate"
    assert counts["/buildings/hq/users"] == counts["/buildings/hq/poses"] == 3  # one per batch's estimate
    assert counts["/buildings/hq/anchors"] >= 1


def test_a_failing_sink_never_reaches_ingestion() -> None:
    broadcaster = Broadcaster()

    def broken(building_id: str, messages: list[object]) -> None:
        raise RuntimeError("viewer gone")

    broadcaster.add_sink(broken)  # type: ignore[arg-type]
    sub = broadcaster.subscribe("hq")
    from schemas.live import HeartbeatMessage

    broadcaster.publish("hq", [HeartbeatMessage(t_ms=1_767_225_600_000, dropped=0)])
    assert broadcaster.sink_errors == 1
    assert sub.queued == 1  # the dashboard still got it


@pytest.mark.parametrize("port", [-1, 70_000])
def test_the_foxglove_port_is_checked(port: int) -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="foxglove_port"):
        Settings(foxglove_port=port)
