"""``crowdslam demo``: migrate the embedded SQLite, start the server, and let a simulated crowd walk."""

from __future__ import annotations

import argparse
import json
import re
import secrets
import signal
import time
from typing import TYPE_CHECKING, Any

from server.cli import tls_options
from server.cli.user_errors import port_number
from server.data import scenario_argument, shipped_scenario

if TYPE_CHECKING:
    from server.tls import TlsFiles


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=port_number, default=8000)
    parser.add_argument(
        "--scenario",
        type=scenario_argument,
        default=shipped_scenario("paper-testbed"),
        metavar="NAME_OR_FILE",
        help="a shipped scenario or a scenario JSON file (default: paper-testbed, the paper's testbed)",
    )
    parser.add_argument("--speed", type=float, default=5.0, help="crowd pace, x real time (0: flat out)")
    parser.add_argument(
        "--crowds", type=int, default=0, help="crowds to walk, one after another (0: forever)"
    )
    # the earlier name of --crowds
    parser.add_argument(
        "--rounds", dest="crowds", type=int, default=argparse.SUPPRESS, help=argparse.SUPPRESS
    )
    parser.add_argument("--building", default="demo")
    tls_options.add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    import httpx

    from schemas.api import KeyScope
    from server.app import create_app
    from server.auth import key_prefix, mint_key
    from server.cli.background_server import ServerDidNotStartError, running_server
    from server.cli.kernel_progress import KernelProgress
    from server.settings import get_settings
    from server.simulation.crowd_client import (
        crowd_epoch_ms,
        device_keys,
        post_crowd,
        prepare_building,
        retire_crowd,
    )
    from server.store.db import make_engine, make_session_factory
    from server.store.migrate import upgrade
    from slam_core.sim.simulation import Scenario, simulate

    # SIGINT and SIGTERM both stop the demo cleanly (its buildings snapshotted): started in the background
    # a program inherits SIGINT ignored, and SIGTERM (docker stop, kill) would end it without a snapshot
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _interrupt)
    settings = get_settings()
    tls = tls_options.tls_files(args, settings, "demo")
    engine = make_engine(settings.resolved_database_url)
    upgrade(engine)
    with make_session_factory(engine).begin() as session:
        operator_key, _ = mint_key(session, KeyScope.OPERATOR)
    engine.dispose()
    scenario = Scenario.from_dict(json.loads(args.scenario.read_text()))
    app = create_app(settings, tune_gc=True, warming=KernelProgress("crowdslam demo"))
    dashboard: str | None = None
    phone: str | None = None
    try:
        with (
            running_server(
                app, args.host, args.port, ws_compression=settings.ws_compression, tls=tls
            ) as base,
            # the demo's own phones post to this very server on loopback: its certificate names the LAN host
            httpx.Client(base_url=base, timeout=60.0, verify=tls is None) as client,
        ):
            sim = simulate(scenario, 0)
            prepare_building(client, args.building, operator_key, sim)
            dashboard = client.post(
                f"/v1/buildings/{args.building}/keys",
                json={"scope": "dashboard"},
                headers={"Authorization": f"Bearer {operator_key}"},
            ).json()["key"]
            phone_device = f"phone-{secrets.token_hex(3)}"
            phone = client.post(
                f"/v1/buildings/{args.building}/keys",
                json={"scope": "device", "device_id": phone_device},
                headers={"Authorization": f"Bearer {operator_key}"},
            ).json()["key"]
            ws_base = base.replace("http", "ws", 1)
            print(f"crowdslam demo: database {settings.resolved_database_url}", flush=True)
            print(f"  dashboard:           {base}/dashboard/#key={dashboard}&building={args.building}")
            print(f"  API docs (OpenAPI):  {base}/docs")
            print(f"  live positions (WS): {ws_base}/v1/buildings/{args.building}/live?token={dashboard}")
            building_url = f"{base}/v1/buildings/{args.building}"
            print(
                f"  latest positions:    curl -H 'Authorization: Bearer {dashboard}' {building_url}/positions"
            )
            print(f"  anchor map:  curl -H 'Authorization: Bearer {operator_key}' {building_url}/anchors")
            print(f"  operator key:        {operator_key}")
            print_phone_link(args.host, args.port, tls, phone, args.building)
            foxglove_live = app.state.crowdslam.foxglove
            if foxglove_live is not None:
                url = f"ws://{settings.foxglove_host}:{foxglove_live.port}"
                print(f"  Foxglove/Lichtblick: {url} (topics /buildings/{args.building}/*)")
            else:
                print("  Foxglove/Lichtblick: set CROWDSLAM_FOXGLOVE_PORT=8765 to watch the crowd there")
            print("  Ctrl-C stops.", flush=True)
            crowd = 0
            # this run's devices and batch ids are its own: a demo run again in the same folder walks new
            # phones, whose batches are not duplicates of the last run's
            run = secrets.token_hex(3)
            left = retire_leftovers(client, args.building, operator_key)
            if left:
                print(f"  {left} people of an earlier demo run left the building", flush=True)
            while args.crowds == 0 or crowd < args.crowds:
                # new people walking the same building (its anchors and access points), after the last crowd;
                # their phones' clocks near the wall clock, so the dashboard's times read as today's
                sim = simulate(scenario, crowd, world_seed=0)
                duration_s = max(float(tr.t[-1]) for tr in sim.users)
                epoch_ms = crowd_epoch_ms(int(time.time() * 1000), duration_s, args.speed)
                prefix = f"{run}-c{crowd}-"
                keys = device_keys(client, args.building, operator_key, len(sim.users), prefix)
                report = post_crowd(client, sim, args.building, keys, args.speed, prefix, epoch_ms=epoch_ms)
                s = report.summary()
                print(
                    f"  crowd {crowd}: {s['batches']} batches, {s['errors']} errors, "
                    f"{s['duplicates']} duplicates, "
                    f"{s['encounters']} encounters, error median {s['median_m']:.2f} m, "
                    f"p90 {s['p90_m']:.2f} m, {s['seconds']:.0f} s; it leaves the building",
                    flush=True,
                )
                retire_crowd(client, args.building, operator_key, {d: key_prefix(k) for d, k in keys.items()})
                crowd += 1
    except ServerDidNotStartError as exc:
        print(f"error: {exc}")
        return 1
    except KeyboardInterrupt:
        pass
    finally:
        revoke_demo_keys(settings.resolved_database_url, args.building, operator_key, dashboard, phone)
    return 0


def print_phone_link(host: str, port: int, tls: TlsFiles | None, key: str, building_id: str) -> None:
    """The phone page's link for a phone of this run, and its QR code when a phone on the network can open it
    (a phone gives motion sensors only to an HTTPS page, or to one on its own localhost)."""
    import segno

    base = tls_options.public_base(host, port, tls)
    link = f"{base}/phone/#key={key}&building={building_id}"
    print(f"  phone page:          {link}")
    if host in tls_options.LOOPBACK or tls is None:
        print(
            "  a real phone:        crowdslam demo --host 0.0.0.0 --tls-self-signed, then scan the QR code "
            "it prints (the phone must be on this network)"
        )
        return
    print("  scan with a phone on this network (accept the self-signed certificate once):")
    segno.make(link, error="m").terminal(compact=True)


def revoke_demo_keys(
    database_url: str, building_id: str, operator_key: str, dashboard: str | None, phone: str | None = None
) -> None:
    """The keys a demo run printed stop working when it stops: its operator key (site-wide), its dashboard
    key and its phone's key. A Ctrl-C meanwhile is not stopped halfway: the revocation is one transaction."""
    from server.auth import key_prefix
    from server.store import repositories as repo
    from server.store.db import make_engine, make_session_factory

    engine = make_engine(database_url)
    try:
        with make_session_factory(engine).begin() as session:
            for building, key in ((None, operator_key), (building_id, dashboard), (building_id, phone)):
                prefix = None if key is None else key_prefix(key)
                if prefix is not None:
                    repo.revoke_keys(session, building, prefix)
    finally:
        engine.dispose()


DEMO_DEVICE = re.compile(r"[0-9a-f]{6}-[cr]\d+-")
"""The demo's device ids: ``<run>-c<crowd>-<device>`` (``-r`` in earlier versions)."""


def retire_leftovers(client: Any, building_id: str, operator_key: str) -> int:
    """The people an earlier demo run left in its building (stopped in the middle of a crowd) are forgotten,
    and their device keys revoked; the number of people."""
    from server.simulation.crowd_client import retire_crowd

    auth = {"Authorization": f"Bearer {operator_key}"}
    users = client.get(f"/v1/buildings/{building_id}/positions", headers=auth).json()
    keys = client.get(f"/v1/buildings/{building_id}/keys", headers=auth).json()
    live = {k["device_id"]: k["prefix"] for k in keys if k["device_id"] and not k["revoked_at"]}
    leftover = {u["user_id"] for u in users if DEMO_DEVICE.match(u["user_id"])}
    leftover |= {d for d in live if DEMO_DEVICE.match(d)}
    return retire_crowd(client, building_id, operator_key, {d: live.get(d) for d in sorted(leftover)})


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt
