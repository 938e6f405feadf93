"""Webhooks end to end: a real HTTP receiver on this machine gets each zone event signed, in order, again
after failures, never by a redirect; a dead receiver neither slows a batch nor keeps a queue without end;
and a webhook never reaches the server's own network unless the server's operator allows it."""

from __future__ import annotations

import hashlib
import hmac
import json
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.cli.background_server import free_port
from server.settings import Settings
from server.webhooks.addresses import AllowedHosts, RefusedAddressError, resolve
from tests.server.api.test_zones import ZONES, _walk, _zone
from tests.server.conftest import migrate_with_operator

SECRET = "a secret of at least sixteen characters"
HOOKS = "/v1/buildings/hq/webhooks"


@dataclass
class Receiver:
    """A local HTTP server recording every POST; ``answer`` picks each one's status (by its order)."""

    url: str
    answer: Callable[[int], int]
    received: list[tuple[dict[str, str], bytes]] = field(default_factory=list)


@contextmanager
def receiver(answer: Callable[[int], int] = lambda n: 200, path: str = "/hook") -> Iterator[Receiver]:
    port = free_port()
    got = Receiver(f"http://127.0.0.1:{port}{path}", answer)

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers["Content-Length"]))
            got.received.append(({k.lower(): v for k, v in self.headers.items()}, body))
            status = got.answer(len(got.received))
            self.send_response(status)
            if 300 <= status < 400:
                self.send_header("Location", f"http://127.0.0.1:{port}/elsewhere")
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield got
    finally:
        server.shutdown()
        server.server_close()


def _until(check: Callable[[], Any], timeout_s: float = 20.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if value := check():
            return value
        time.sleep(0.05)
    raise AssertionError("not in time")


def _walk_through(client: TestClient, device: dict[str, str], seqs: range, user: str = "phone-1") -> None:
    for seq in seqs:
        r = client.post("/v1/buildings/hq/batches", json=_walk(seq, user), headers=device)
        assert r.status_code == 200, r.text


@dataclass(frozen=True)
class Site:
    """A migrated database holding building ``hq`` (60 x 50 m), the operator's and ``phone-1``'s keys, and
    the settings to serve it with (one app at a time: each app's dispatcher sends what is due)."""

    settings: Settings
    op: dict[str, str]
    device: dict[str, str]

    def serve(self, **settings: Any) -> TestClient:
        return TestClient(create_app(self.settings.model_copy(update=settings)))


def _site(url: str, data: Path) -> Site:
    operator = migrate_with_operator(url)
    settings = Settings(data_dir=data, database_url=url, record=False)
    op = {"Authorization": f"Bearer {operator}"}
    with TestClient(create_app(settings)) as client:
        floors = [{"level": 0, "name": "Ground", "width_m": 60.0, "height_m": 50.0}]
        assert (
            client.post(
                "/v1/buildings", json={"id": "hq", "name": "HQ", "floors": floors}, headers=op
            ).status_code
            == 201
        )
        key = client.post(
            "/v1/buildings/hq/keys", json={"scope": "device", "device_id": "phone-1"}, headers=op
        )
        device = {"Authorization": f"Bearer {key.json()['key']}"}
    return Site(settings, op, device)


@pytest.fixture
def site(database_url: str, tmp_path: Path) -> Site:
    return _site(database_url, tmp_path)


@pytest.fixture
def sqlite_site(sqlite_url: str, tmp_path: Path) -> Site:
    return _site(sqlite_url, tmp_path)


def test_events_are_delivered_signed_in_order_and_again_after_failures(site: Site) -> None:
    op, device = site.op, site.device
    fails = {1, 2}  # the first delivery's first two tries fail
    served = site.serve(webhook_allowed_hosts="127.0.0.1/32", webhook_retry_s=0.05)
    with receiver(lambda n: 500 if n in fails else 200) as got, served as client:
        assert client.put(f"{ZONES}/front", json=_zone(9, 15, dwell_s=1.0), headers=op).status_code == 200
        hook = {"url": got.url, "secret": SECRET, "events": ["zone.enter", "zone.exit", "zone.dwell"]}
        put = client.put(f"{HOOKS}/app", json=hook, headers=op)
        assert put.status_code == 200, put.text
        assert put.json() == {"id": "app", "url": got.url, "events": hook["events"], "suspended": False}
        _walk_through(client, device, range(14))  # in at ~9 m, dwell, out at ~15 m
        _until(lambda: len(got.received) >= 5)
        time.sleep(0.3)
        log = client.get(f"{HOOKS}/app/deliveries", headers=op).json()
    assert len(got.received) == 5  # three events, the first sent three times
    bodies = [json.loads(body) for _, body in got.received]
    assert [b["event"] for b in bodies] == ["zone.enter"] * 3 + ["zone.dwell", "zone.exit"]
    assert bodies[0] == bodies[1] == bodies[2]  # the same event (and id) again
    assert len({b["id"] for b in bodies}) == 3
    assert all(b["zone_id"] == "front" and b["user_id"] == "phone-1" for b in bodies)
    assert [b["t_ms"] for b in bodies] == sorted(b["t_ms"] for b in bodies)
    for headers, body in got.received:
        expected = "sha256=" + hmac.new(SECRET.encode(), body, hashlib.sha256).hexdigest()
        assert headers["x-crowdslam-signature"] == expected
        assert headers["content-type"] == "application/json"
        assert headers["host"] == got.url.split("/")[2]
    assert [(d["event"], d["status"], d["attempts"], d["http_status"]) for d in log] == [
        ("zone.exit", "delivered", 1, 200),
        ("zone.dwell", "delivered", 1, 200),
        ("zone.enter", "delivered", 3, 200),
    ]
    assert SECRET not in json.dumps(log)


def test_a_dead_receiver_slows_no_batch_and_is_suspended_after_its_tries(site: Site) -> None:
    op, device = site.op, site.device
    dead = f"http://127.0.0.1:{free_port()}/hook"  # nobody listens
    with site.serve(
        webhook_allowed_hosts="127.0.0.1", webhook_retry_s=0.05, webhook_max_attempts=3
    ) as client:
        assert client.put(f"{ZONES}/front", json=_zone(9, 15), headers=op).status_code == 200
        hook = {"url": dead, "secret": SECRET, "events": ["zone.enter", "zone.exit"]}
        assert client.put(f"{HOOKS}/app", json=hook, headers=op).status_code == 200
        _walk_through(client, device, range(14))
        hooks = _until(lambda: [h for h in client.get(HOOKS, headers=op).json() if h["suspended"]])
        assert hooks[0]["id"] == "app"
        log = client.get(f"{HOOKS}/app/deliveries", headers=op).json()
        assert [(d["event"], d["status"]) for d in log] == [
            ("zone.exit", "gave_up"),
            ("zone.enter", "gave_up"),
        ]
        assert log[1]["attempts"] == 3
        assert "ConnectError" in log[1]["error"]
        assert log[0]["attempts"] == 0  # given up with its webhook, never tried
        assert "suspended" in log[0]["error"]
        # suspended: later events queue nothing; PUT again takes events again
        _walk_through(client, device, range(14, 16))
        assert client.put(f"{HOOKS}/app", json=hook, headers=op).json()["suspended"] is False


def test_redirects_are_not_followed(sqlite_site: Site) -> None:
    op, device = sqlite_site.op, sqlite_site.device
    served = sqlite_site.serve(
        webhook_allowed_hosts="127.0.0.1", webhook_retry_s=0.05, webhook_max_attempts=2
    )
    with receiver(lambda n: 302) as got, served as client:
        assert client.put(f"{ZONES}/front", json=_zone(9, 15), headers=op).status_code == 200
        hook = {"url": got.url, "secret": SECRET, "events": ["zone.enter"]}
        assert client.put(f"{HOOKS}/app", json=hook, headers=op).status_code == 200
        _walk_through(client, device, range(8))
        log = _until(
            lambda: [
                d
                for d in client.get(f"{HOOKS}/app/deliveries", headers=op).json()
                if d["status"] != "pending"
            ]
        )
    assert log[0]["http_status"] == 302
    assert "redirect" in log[0]["error"]
    assert len(got.received) == 2  # two tries, at the hook's path only: /elsewhere was never asked


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:9/hook",
        "http://localhost:9/hook",
        "http://169.254.169.254/latest/meta-data",
        "http://10.1.2.3/hook",
        "http://[::1]:9/hook",
        "http://[::ffff:127.0.0.1]:9/hook",
        "http://0.0.0.0/hook",
    ],
)
def test_a_webhook_may_not_reach_the_servers_network(sqlite_site: Site, url: str) -> None:
    op = sqlite_site.op
    hook = {"url": url, "secret": SECRET, "events": ["zone.enter"]}
    with sqlite_site.serve() as client:
        r = client.put(f"{HOOKS}/in", json=hook, headers=op)
        assert r.status_code == 422, r.text
        assert "not a public address" in r.json()["detail"]
        assert client.get(HOOKS, headers=op).json() == []


def test_bad_webhooks_are_refused(sqlite_site: Site) -> None:
    op = sqlite_site.op
    with sqlite_site.serve() as client:
        dashboard_key = client.post("/v1/buildings/hq/keys", json={"scope": "dashboard"}, headers=op).json()[
            "key"
        ]
        _refused(client, op, {"Authorization": f"Bearer {dashboard_key}"})


def _refused(client: TestClient, op: dict[str, str], dashboard: dict[str, str]) -> None:
    good = {"url": "https://example.com/hook", "secret": SECRET, "events": ["zone.enter"]}
    for body, says in [
        (good | {"url": "ftp://example.com/x"}, "url"),
        (good | {"url": "https://user:pw@example.com/x"}, "credentials"),
        (good | {"secret": "short"}, "secret"),
        (good | {"events": ["zone.teleport"]}, "events"),
        (good | {"events": ["zone.enter", "zone.enter"]}, "each event once"),
    ]:
        r = client.put(f"{HOOKS}/x", json=body, headers=op)
        assert r.status_code == 422, body
        assert says in r.text
    assert client.put(f"{HOOKS}/x", json=good, headers=dashboard).status_code == 403
    assert client.get(HOOKS, headers=dashboard).status_code == 403
    assert client.delete(f"{HOOKS}/x", headers=op).status_code == 404
    assert client.get(f"{HOOKS}/x/deliveries", headers=op).status_code == 404


def test_the_address_is_checked_at_every_delivery() -> None:
    """A host allowed when the webhook was stored and not at delivery is refused then; names and networks
    of the allowance; a name resolving to any private address is refused."""
    allowed = AllowedHosts.parse(" receiver.internal , 127.0.0.0/8,::1 ")
    assert str(resolve("127.0.0.5", 80, allowed)) == "127.0.0.5"
    assert str(resolve("::1", 80, allowed)) == "::1"
    with pytest.raises(RefusedAddressError, match="not a public address"):
        resolve("10.0.0.1", 80, allowed)
    assert str(resolve("localhost", 80, AllowedHosts.parse("localhost"))) in ("127.0.0.1", "::1")
    with pytest.raises(RefusedAddressError):
        resolve("localhost", 80, AllowedHosts.parse(""))
    with pytest.raises(RefusedAddressError, match="does not resolve"):
        resolve("no-such-host.invalid", 80, allowed)
    with pytest.raises(ValueError, match="neither a host name nor a CIDR"):
        AllowedHosts.parse("10.0.0.0/8,not a host!")


def test_a_delivery_to_an_address_no_longer_allowed_gives_up(sqlite_site: Site) -> None:
    op, device = sqlite_site.op, sqlite_site.device
    with receiver() as got:
        with sqlite_site.serve(webhook_allowed_hosts="127.0.0.1") as client:
            assert client.put(f"{ZONES}/front", json=_zone(9, 15), headers=op).status_code == 200
            hook = {"url": got.url, "secret": SECRET, "events": ["zone.enter"]}
            assert client.put(f"{HOOKS}/app", json=hook, headers=op).status_code == 200
        with sqlite_site.serve() as client:  # the allowance withdrawn
            _walk_through(client, device, range(8))
            log = _until(
                lambda: [
                    d
                    for d in client.get(f"{HOOKS}/app/deliveries", headers=op).json()
                    if d["status"] != "pending"
                ]
            )
    assert log[0]["status"] == "gave_up"
    assert log[0]["attempts"] == 1
    assert "not a public address" in log[0]["error"]
    assert got.received == []


def test_a_bad_allowance_stops_the_server_naming_it(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, webhook_allowed_hosts="10.0.0.0/8,not a host!")
    with pytest.raises(ValueError, match="CROWDSLAM_WEBHOOK_ALLOWED_HOSTS: 'not a host!'"):
        create_app(settings)
