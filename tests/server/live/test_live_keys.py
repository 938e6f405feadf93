"""A browser's live socket: the key as a subprotocol (no key in a URL that logs keep), and a key revoked
while its socket is open closes it with 4401."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from server.api.live import KEY_RECHECK_S, SUBPROTOCOL
from server.app import create_app
from server.cli.background_server import free_port, running_server
from server.live.broadcast import Broadcaster
from server.settings import Settings
from tests.server.api.test_api import _batch
from tests.server.conftest import migrate_with_operator


def test_the_key_rides_as_a_subprotocol_and_revocation_closes_the_socket(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    operator = migrate_with_operator(url)
    app = create_app(Settings(data_dir=tmp_path, database_url=url))
    with running_server(app, "127.0.0.1", free_port()) as base:
        op = {"Authorization": f"Bearer {operator}"}
        assert (
            httpx.post(f"{base}/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=op).status_code == 201
        )
        minted = httpx.post(f"{base}/v1/buildings/hq/keys", json={"scope": "dashboard"}, headers=op).json()
        device = httpx.post(
            f"{base}/v1/buildings/hq/keys", json={"scope": "device", "device_id": "phone-1"}, headers=op
        ).json()["key"]
        live = base.replace("http://", "ws://") + "/v1/buildings/hq/live"
        with connect(live, subprotocols=[SUBPROTOCOL, f"bearer.{minted['key']}"], open_timeout=10) as ws:  # type: ignore[list-item]
            assert ws.subprotocol == SUBPROTOCOL
            posted = httpx.post(
                f"{base}/v1/buildings/hq/batches",
                json=_batch(0),
                headers={"Authorization": f"Bearer {device}"},
            )
            assert posted.status_code == 200
            assert '"type":"position"' in str(ws.recv(timeout=10))
            revoked = httpx.delete(f"{base}/v1/buildings/hq/keys/{minted['prefix']}", headers=op)
            assert revoked.status_code == 204
            started = time.monotonic()
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=10)  # nothing else is sent before the close: no batch, no heartbeat yet
            assert closed.value.rcvd is not None
            assert (closed.value.rcvd.code, closed.value.rcvd.reason) == (4401, "key revoked")
            assert time.monotonic() - started < KEY_RECHECK_S + 2
        # a refused key is refused with its code, on a handshake a browser accepts (a subprotocol chosen)
        with connect(live, subprotocols=[SUBPROTOCOL, "bearer.csk_00000000_nope"], open_timeout=10) as ws:  # type: ignore[list-item]
            assert ws.subprotocol == SUBPROTOCOL
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=10)
            assert closed.value.rcvd is not None
            assert closed.value.rcvd.code == 4401


@contextlib.contextmanager
def _dashboard_socket(settings: Settings) -> Iterator[tuple[str, Broadcaster]]:
    """A server with building hq: its live socket's URL with a dashboard key, and the server's broadcaster."""
    operator = migrate_with_operator(settings.resolved_database_url)
    app = create_app(settings)
    with running_server(app, "127.0.0.1", free_port()) as base:
        op = {"Authorization": f"Bearer {operator}"}
        assert (
            httpx.post(f"{base}/v1/buildings", json={"id": "hq", "name": "HQ"}, headers=op).status_code == 201
        )
        key = httpx.post(f"{base}/v1/buildings/hq/keys", json={"scope": "dashboard"}, headers=op).json()[
            "key"
        ]
        live = base.replace("http://", "ws://") + f"/v1/buildings/hq/live?token={key}"
        yield live, app.state.crowdslam.broadcaster


def _assert_unsubscribed_soon(broadcaster: Broadcaster) -> None:
    """The closed socket's subscription is gone within 2 s (not at the next heartbeat, 10 s away)."""
    deadline = time.monotonic() + 2.0
    while broadcaster.subscribers("hq") and time.monotonic() < deadline:
        time.sleep(0.02)
    assert broadcaster.subscribers("hq") == 0


def test_a_closed_socket_gives_its_slot_back_at_once(tmp_path: Path) -> None:
    """Dashboards send nothing: the server reads its sockets all the same, so a dashboard that leaves a quiet
    building frees its subscription and its place under the key's socket limit at once, not at the next
    heartbeat, and a dashboard reloaded at once is let in."""
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    with _dashboard_socket(Settings(data_dir=tmp_path, database_url=url, max_live_sockets_per_key=1)) as (
        live,
        broadcaster,
    ):
        for _ in range(3):
            with connect(live, open_timeout=10) as ws:
                with pytest.raises(TimeoutError):
                    ws.recv(timeout=0.3)  # let in: nothing to say in a quiet building, not a 4429 close
                assert broadcaster.subscribers("hq") == 1
            _assert_unsubscribed_soon(broadcaster)


def test_a_live_socket_takes_no_messages(tmp_path: Path) -> None:
    """A client that sends on its live socket is closed with 1008 and lets its subscription go; a frame past
    ``max_ws_frame_bytes`` is refused before it is read whole (1009), here as on the batch stream."""
    settings = Settings(
        data_dir=tmp_path, database_url=f"sqlite:///{tmp_path / 'db.sqlite3'}", max_batch_bytes=4096
    )
    with _dashboard_socket(settings) as (live, broadcaster):
        for frame, code in (("hello", 1008), ("x" * (settings.max_ws_frame_bytes + 1), 1009)):
            with connect(live, open_timeout=10) as ws:
                ws.send(frame)
                with pytest.raises(ConnectionClosed) as closed:
                    ws.recv(timeout=5)
                assert closed.value.rcvd is not None
                assert closed.value.rcvd.code == code
            _assert_unsubscribed_soon(broadcaster)
