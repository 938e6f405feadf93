"""WebSocket refusals reach a real client as the documented close codes with their reasons (a socket closed
before it was accepted had reached it as a bare HTTP 403)."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from server.app import create_app
from server.cli.background_server import free_port, running_server
from server.settings import Settings
from tests.server.conftest import migrate_with_operator


def _closed(url: str) -> tuple[int, str]:
    with connect(url, open_timeout=10) as ws, pytest.raises(ConnectionClosed) as closed:
        ws.recv(timeout=10)
    assert closed.value.rcvd is not None
    return closed.value.rcvd.code, closed.value.rcvd.reason


def test_refusals_close_with_their_codes(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    app = create_app(Settings(data_dir=tmp_path, database_url=url))
    with running_server(app, "127.0.0.1", free_port()) as base:
        auth = {"Authorization": f"Bearer {operator}"}
        created = httpx.post(f"{base}/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=auth)
        assert created.status_code == 201
        device = httpx.post(
            f"{base}/v1/buildings/hq/keys", json={"scope": "device", "device_id": "p1"}, headers=auth
        ).json()["key"]
        ws = base.replace("http://", "ws://")
        code, reason = _closed(f"{ws}/v1/buildings/hq/live?token=nope")
        assert code == 4401
        assert reason
        code, reason = _closed(f"{ws}/v1/buildings/hq/live?token={device}")  # a device key cannot watch
        assert code == 4403
        assert reason
        code, reason = _closed(f"{ws}/v1/buildings/nowhere/live?token={operator}")
        assert (code, reason) == (4404, "no building 'nowhere'")
        code, reason = _closed(f"{ws}/v1/buildings/hq/stream?token=nope")
        assert (code, reason) == (4401, "unknown or missing key")


def test_a_streamed_frame_is_bounded_before_it_is_read(tmp_path: Path) -> None:
    """On the batch stream a frame just past ``max_batch_bytes`` is answered with its 413 and the stream
    goes on; one past ``max_ws_frame_bytes`` closes the socket (1009) before the server holds it whole
    (uvicorn's own bound is 16 MiB)."""
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=tmp_path, database_url=url, max_batch_bytes=8192)
    with running_server(create_app(settings), "127.0.0.1", free_port()) as base:
        auth = {"Authorization": f"Bearer {operator}"}
        assert httpx.post(f"{base}/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=auth).is_success
        device = httpx.post(
            f"{base}/v1/buildings/hq/keys", json={"scope": "device", "device_id": "p1"}, headers=auth
        ).json()["key"]
        stream = base.replace("http://", "ws://") + f"/v1/buildings/hq/stream?token={device}"
        with connect(stream, open_timeout=10) as ws:
            ws.send(" " * (settings.max_batch_bytes + 1))
            assert '"status":413' in str(ws.recv(timeout=10))
            ws.send(" " * (settings.max_ws_frame_bytes + 1))
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=10)
            assert closed.value.rcvd is not None
            assert closed.value.rcvd.code == 1009
