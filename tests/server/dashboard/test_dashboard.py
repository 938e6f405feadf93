"""The dashboard as people use it, in headless Chromium against a running demo: log in (link and form), see
the crowd move, pin an anchor, be refused what the key may not do, outlive a server restart, and be logged
out when the key is revoked; the page and the API docs never reach past loopback or log a console error."""

from __future__ import annotations

import io
import json
import os
import re
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import httpx
import numpy as np
import pytest
import zxingcpp
from PIL import Image
from playwright.sync_api import Browser, Page, expect

from schemas.floor_plans import FLOOR_PLAN_EXAMPLE
from schemas.signal_maps import SignalMapJob, SignalMapStatus
from server.cli.background_server import free_port, migrate_with_operator_key, serve_process
from server.datasets.signalslam_plots import write_scan_maps
from server.signal_maps.jobs import RECORD
from tests.server.dashboard.conftest import Demo, Watch, open_page, wait_for


def root_data(page: Page, name: str) -> str:
    value = page.locator("#app").get_attribute(f"data-{name}")
    return value or ""


def auth(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def test_the_link_logs_in_and_the_crowd_moves_as_the_api_says(browser: Browser, demo: Demo) -> None:
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(demo.dashboard_link)
    expect(page.locator("#app")).to_have_attribute("data-building", demo.building, timeout=20_000)
    expect(page.locator("#app")).to_have_attribute("data-connection", "connected", timeout=20_000)
    assert "key=" not in page.url  # the key left the address bar (and the history) at once
    wait_for(lambda: int(root_data(page, "updated-ms")) > 0, 60, "the crowd's first estimates drawn")
    first = int(root_data(page, "updated-ms"))
    wait_for(lambda: int(root_data(page, "updated-ms")) > first, 30, "data-updated-ms advances")

    def drawn_matches_api() -> bool:
        listed = httpx.get(
            f"{demo.base}/v1/buildings/demo/positions", headers=auth(demo.dashboard_key)
        ).json()
        return int(root_data(page, "users")) == len(listed) > 0

    wait_for(drawn_matches_api, 20, "data-users equals the API's positions")
    # the floor list says how many people each floor has (read with data-users at once: they change together)
    label, users = page.evaluate(
        "() => [document.querySelector('#floor option').textContent,"
        " document.getElementById('app').dataset.users]"
    )
    assert label.endswith(f" {users} people")
    # an encounter is drawn where the two met, on its own floor only (these two ids are nobody on the map)
    drawn = page.evaluate(
        """() => {
          const d = window.crowdslamDashboard, now = performance.now();
          const met = (floor) => ({ user_a: "gone-a", user_b: "gone-b", floor, applied: true, seenMs: now,
            position_a: { x_m: 1, y_m: 1 }, position_b: { x_m: 3, y_m: 2 } });
          const scene = { floor: d.scene.floor, users: new Map() };
          scene.encounters = [met(d.scene.floor + 1)];
          const above = d.view.drawEncounters(scene, now);
          scene.encounters = [met(d.scene.floor)];
          return [above, d.view.drawEncounters(scene, now)];
        }"""
    )
    assert drawn == [False, True]
    # a person's details: id, sigma, last update
    page.evaluate(
        "() => { const d = window.crowdslamDashboard;"
        " d.scene.selectedUser = [...d.scene.users.keys()][0]; d.renderDetails(); }"
    )
    details = page.locator("#details-body").inner_text()
    assert "sigma" in details
    assert "last update" in details
    expect(page.locator("#tools")).to_be_hidden()  # a dashboard key sees no operator tools
    # the keyboard zooms and pans the map, and 0 fits the floor again
    fitted = page.evaluate("() => window.crowdslamDashboard.view.scale")
    page.locator("#map").focus()
    page.keyboard.press("+")
    assert page.evaluate("() => window.crowdslamDashboard.view.scale") > fitted
    before = page.evaluate("() => window.crowdslamDashboard.view.ox")
    page.keyboard.press("ArrowLeft")
    assert page.evaluate("() => window.crowdslamDashboard.view.ox") > before
    page.keyboard.press("0")
    assert page.evaluate("() => window.crowdslamDashboard.view.scale") == fitted
    watch.assert_clean()
    page.context.close()


def test_a_building_the_server_fails_is_named_on_its_page(browser: Browser, demo: Demo) -> None:
    """/healthz names a failing building (the server's own error): its page says so in a badge, and says
    nothing once /healthz no longer names it."""
    watch = Watch()
    page = open_page(browser, watch)
    failing = {
        "status": "degraded",
        "database": "sqlite",
        "buildings_loaded": 1,
        "failing_buildings": [
            {
                "building_id": demo.building,
                "failed_batches": 3,
                "unreplayed_batches": 0,
                "failed_loads": 0,
                "last_failure_ms": int(time.time() * 1000),
            }
        ],
        "disk_free_bytes": 1,
        "low_disk": False,
    }
    page.route("**/healthz", lambda route: route.fulfill(json=failing))
    page.goto(demo.dashboard_link)
    expect(page.locator("#health")).to_be_visible(timeout=20_000)
    expect(page.locator("#health")).to_contain_text("3 batches failed")
    assert root_data(page, "failing") == "true"
    page.unroute("**/healthz")
    page.evaluate("() => window.crowdslamDashboard.watchHealth(window.crowdslamDashboard.building.id)")
    expect(page.locator("#health")).to_be_hidden(timeout=10_000)
    watch.assert_clean()
    page.context.close()


def test_the_form_logs_in_and_a_wrong_key_is_told_why(browser: Browser, demo: Demo) -> None:
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(f"{demo.base}/")  # the root leads to the dashboard
    assert page.url.endswith("/dashboard/")
    page.fill("#key-input", "csk_00000000_not-a-key")
    page.click("#login-form button[type=submit]")
    expect(page.locator("#login-message")).to_contain_text("key", timeout=10_000)
    assert root_data(page, "building") == ""
    page.fill("#key-input", demo.dashboard_key)
    page.click("#login-form button[type=submit]")
    expect(page.locator("#app")).to_have_attribute("data-building", demo.building, timeout=20_000)
    expect(page.locator("#building-name")).not_to_be_empty()
    assert watch.off_loopback == []
    # the browser's own note of the wrong key's 401, and nothing else
    assert watch.console_errors == [
        "Failed to load resource: the server responded with a status of 401 (Unauthorized)"
    ]
    page.context.close()


def test_an_operator_pins_an_anchor_and_the_api_has_it(browser: Browser, demo: Demo) -> None:
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(f"{demo.base}/dashboard/#key={demo.operator_key}&building={demo.building}")
    expect(page.locator("#app")).to_have_attribute("data-building", demo.building, timeout=20_000)
    expect(page.locator("#tools")).to_be_visible()
    page.select_option("#pin-type", "elevator")
    page.fill("#pin-label", "lift by the atrium")
    page.fill("#pin-x", "12.5")
    page.fill("#pin-y", "31")
    page.click("#pin-submit")
    expect(page.locator("#message")).to_contain_text("Pinned elevator anchor", timeout=10_000)
    anchors = httpx.get(f"{demo.base}/v1/buildings/demo/anchors", headers=auth(demo.dashboard_key)).json()
    pinned = [a for a in anchors if a["label"] == "lift by the atrium"]
    assert len(pinned) == 1
    assert pinned[0]["known"] is True
    assert pinned[0]["type"] == "elevator"
    assert (pinned[0]["position"]["x_m"], pinned[0]["position"]["y_m"]) == (12.5, 31.0)
    # and deletes it again through the page (the button asks twice)
    page.click("#anchor-delete")
    page.click("#anchor-delete")
    expect(page.locator("#message")).to_contain_text(f"Deleted {pinned[0]['id']}", timeout=10_000)
    anchors = httpx.get(f"{demo.base}/v1/buildings/demo/anchors", headers=auth(demo.dashboard_key)).json()
    assert all(a["id"] != pinned[0]["id"] for a in anchors)
    # a position picked on the map (two decimals: the inputs must take them)
    page.click("#pin-pick")
    page.locator("#map").click(position={"x": 300, "y": 300})
    picked = float(page.input_value("#pin-x")), float(page.input_value("#pin-y"))
    page.fill("#pin-label", "picked")
    page.click("#pin-submit")
    expect(page.locator("#message")).to_contain_text("Pinned elevator anchor", timeout=10_000)
    anchors = httpx.get(f"{demo.base}/v1/buildings/demo/anchors", headers=auth(demo.dashboard_key)).json()
    placed = [a["position"] for a in anchors if a["label"] == "picked"]
    assert [(p["x_m"], p["y_m"]) for p in placed] == [picked]
    watch.assert_clean()
    page.context.close()


def test_a_dashboard_key_is_refused_an_operator_tool_and_sees_why(browser: Browser, demo: Demo) -> None:
    page = open_page(browser, Watch())
    page.goto(demo.dashboard_link)
    expect(page.locator("#app")).to_have_attribute("data-building", demo.building, timeout=20_000)
    expect(page.locator("#tools")).to_be_hidden()
    before = httpx.get(f"{demo.base}/v1/buildings/demo/anchors", headers=auth(demo.dashboard_key)).json()
    # a person who unhides the tools still goes through the API, which refuses and says why
    page.evaluate("() => { document.getElementById('tools').hidden = false; }")
    page.fill("#pin-x", "5")
    page.fill("#pin-y", "5")
    page.click("#pin-submit")
    expect(page.locator("#message")).to_contain_text("needs an operator key", timeout=10_000)
    after = httpx.get(f"{demo.base}/v1/buildings/demo/anchors", headers=auth(demo.dashboard_key)).json()
    assert after == before
    page.context.close()


def test_a_revoked_key_logs_the_page_out(browser: Browser, demo: Demo) -> None:
    minted = httpx.post(
        f"{demo.base}/v1/buildings/demo/keys", json={"scope": "dashboard"}, headers=auth(demo.operator_key)
    ).json()
    page = open_page(browser, Watch())
    page.goto(f"{demo.base}/dashboard/#key={minted['key']}&building={demo.building}")
    expect(page.locator("#app")).to_have_attribute("data-connection", "connected", timeout=20_000)
    revoked = httpx.delete(
        f"{demo.base}/v1/buildings/demo/keys/{minted['prefix']}", headers=auth(demo.operator_key)
    )
    assert revoked.status_code == 204
    expect(page.locator("#login")).to_be_visible(timeout=15_000)
    expect(page.locator("#login-message")).to_contain_text("Logged out")
    assert root_data(page, "building") == ""
    assert page.evaluate("() => sessionStorage.getItem('crowdslam.key')") is None
    page.context.close()


def test_the_api_docs_work_offline(browser: Browser, demo: Demo) -> None:
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(f"{demo.base}/docs")
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("crowdslam", timeout=20_000)
    page.goto(f"{demo.base}/redoc")
    expect(page.locator("h1").first).to_contain_text("crowdslam", timeout=20_000)
    watch.assert_clean()
    page.context.close()


def test_the_page_reconnects_after_the_server_restarts(browser: Browser, tmp_path: Path) -> None:
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(tmp_path)}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    operator = migrate_with_operator_key(env)
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = serve_process(env, port, tmp_path / "server.log")
    try:
        building = {
            "id": "hq",
            "name": "HQ",
            "floors": [{"level": 0, "name": "Ground", "width_m": 40, "height_m": 30}],
        }
        assert httpx.post(f"{base}/v1/buildings", json=building, headers=auth(operator)).status_code == 201
        key = httpx.post(
            f"{base}/v1/buildings/hq/keys", json={"scope": "dashboard"}, headers=auth(operator)
        ).json()["key"]
        page = open_page(browser, Watch())
        page.goto(f"{base}/dashboard/#key={key}&building=hq")
        expect(page.locator("#app")).to_have_attribute("data-connection", "connected", timeout=20_000)
        server.terminate()
        server.wait(timeout=60)
        expect(page.locator("#app")).to_have_attribute("data-connection", "reconnecting", timeout=10_000)
        expect(page.locator("#connection")).to_contain_text("disconnected")
        server = serve_process(env, port, tmp_path / "server.log")
        expect(page.locator("#app")).to_have_attribute("data-connection", "connected", timeout=45_000)
        assert root_data(page, "building") == "hq"
        page.context.close()
    finally:
        server.terminate()
        server.wait(timeout=60)


@pytest.fixture(autouse=True)
def _no_proxy(monkeypatch: pytest.MonkeyPatch) -> None:
    # httpx would route loopback requests through a proxy set in the environment
    for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        monkeypatch.delenv(name, raising=False)


def test_a_finished_signal_map_is_an_overlay_chosen_by_access_point(browser: Browser, demo: Demo) -> None:
    """A build's outputs, written by the build's own writer, appear as overlays the page draws in colour."""
    rng = np.random.default_rng(0)
    xy = rng.uniform([0, 0], [60, 50], size=(300, 2))
    aps = np.array([[10.0, 10.0], [50.0, 40.0]])
    distance = np.linalg.norm(xy[:, None, :] - aps[None], axis=2)
    rss = -35 - 30 * np.log10(np.maximum(distance, 1.0)) + rng.normal(0, 2, (300, 2))
    folder = demo.data_dir / "signal_maps" / demo.building / "0a1b2c3d4e5f"
    files = [p.name for p in write_scan_maps(folder, xy, rss, ["aa:bb:cc:00:00:01", "aa:bb:cc:00:00:02"])]
    now = datetime.now(UTC)
    job = SignalMapJob(
        id="0a1b2c3d4e5f", building_id=demo.building, status=SignalMapStatus.DONE, created_at=now,
        finished_at=now, recordings=1, files=files,
    )  # fmt: skip
    (folder / RECORD).write_text(job.model_dump_json())
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(demo.dashboard_link)
    expect(page.locator("#app")).to_have_attribute("data-building", demo.building, timeout=20_000)
    expect(page.locator("#overlay option")).to_have_count(3, timeout=10_000)  # none, AP 1, AP 2
    page.select_option("#overlay", "signal_map_ap1.json")
    expect(page.locator("#overlay-note")).to_contain_text("aa:bb:cc:00:00:0", timeout=10_000)
    expect(page.locator("#legend")).to_contain_text("dBm")
    overlay = page.evaluate(
        "() => { const o = window.crowdslamDashboard.scene.overlay; return [o.rows, o.cols, o.lo, o.hi]; }"
    )
    assert overlay[0] > 5
    assert overlay[1] > 5
    assert -95 < overlay[2] < overlay[3] < -30

    def pixel_at_floor_centre() -> list[int]:
        page.wait_for_timeout(200)  # a frame drawn
        return list(
            page.evaluate(
                "() => { const d = window.crowdslamDashboard; const [x, y] = d.view.toScreen(30, 25);"
                " const r = window.devicePixelRatio || 1; const c = document.getElementById('map');"
                " return [...c.getContext('2d').getImageData(x * r, y * r, 1, 1).data]; }"
            )
        )

    coloured = pixel_at_floor_centre()
    assert coloured[:3] != [255, 255, 255], "the overlay is not drawn"
    page.select_option("#overlay", "")
    assert pixel_at_floor_centre()[:3] != coloured[:3]
    assert page.evaluate("() => window.crowdslamDashboard.scene.overlay") is None
    # a later build of two floors: the page offers the maps of the floor it shows, not the other's
    later = demo.data_dir / "signal_maps" / demo.building / "0a1b2c3d4e60"
    named = []
    for level, ap in ((0, "aa:bb:cc:00:00:01"), (1, "aa:bb:cc:00:00:02")):
        for path in write_scan_maps(later, xy, rss[:, [0]] if level == 0 else rss[:, [1]], [ap], aps=1):
            named.append(path.rename(later / f"floor{level}_{path.name}").name)
    job = job.model_copy(
        update={
            "id": "0a1b2c3d4e60",
            "files": named,
            "floors": [0, 1],
            "finished_at": now + timedelta(seconds=1),
        }
    )
    (later / RECORD).write_text(job.model_dump_json())
    page.evaluate("() => window.crowdslamDashboard.loadOverlays()")
    expect(page.locator("#overlay option")).to_have_count(2, timeout=10_000)  # none, floor 0's AP
    assert page.locator("#overlay option").nth(1).get_attribute("value") == "floor0_signal_map_ap1.json"
    watch.assert_clean()
    page.context.close()


def test_an_operator_uploads_a_plan_and_moves_an_anchor_by_dragging(
    browser: Browser, demo: Demo, tmp_path: Path
) -> None:
    op = auth(demo.operator_key)
    floor = {"level": 0, "name": "Ground", "width_m": 60, "height_m": 50}
    created = httpx.post(
        f"{demo.base}/v1/buildings", json={"id": "annex", "name": "Annex", "floors": [floor]}, headers=op
    )
    assert created.status_code == 201, created.text
    pinned = {"type": "door", "position": {"x_m": 40.0, "y_m": 20.0}}
    # the new building's first request starts its process (its kernels loaded from the cache): seconds on a
    # busy machine, more than httpx's default 5 s
    pin = httpx.put(f"{demo.base}/v1/buildings/annex/anchors/door-1", json=pinned, headers=op, timeout=60.0)
    assert pin.status_code == 200, pin.text
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(f"{demo.base}/dashboard/#key={demo.operator_key}&building=annex")
    expect(page.locator("#app")).to_have_attribute("data-building", "annex", timeout=20_000)
    # a plan from a file, through the page
    plan_file = tmp_path / "annex.geojson"
    plan_file.write_text(json.dumps(FLOOR_PLAN_EXAMPLE))
    page.set_input_files("#plan-file", str(plan_file))
    page.click("#plan-form button[type=submit]")
    expect(page.locator("#message")).to_contain_text("plan uploaded", timeout=10_000)
    stored = httpx.get(f"{demo.base}/v1/buildings/annex/floors/0/plan", headers=op).json()
    assert [f["properties"]["kind"] for f in stored["features"]] == ["walkable", "obstacle", "wall"]
    page.wait_for_function(
        "() => window.crowdslamDashboard.scene.plan?.features.length === 3", timeout=10_000
    )
    # a plan the server refuses shows why, and changes nothing
    plan_file.write_text(json.dumps({"type": "FeatureCollection", "features": [{"type": "Feature"}]}))
    page.set_input_files("#plan-file", str(plan_file))
    page.click("#plan-form button[type=submit]")
    expect(page.locator("#message")).to_contain_text("features.0", timeout=10_000)
    assert httpx.get(f"{demo.base}/v1/buildings/annex/floors/0/plan", headers=op).json() == stored
    # select the anchor, then drag it 10 m east
    box = page.locator("#map").bounding_box()
    assert box is not None
    x, y = page.evaluate("() => window.crowdslamDashboard.view.toScreen(40, 20)")
    scale = page.evaluate("() => window.crowdslamDashboard.view.scale")
    page.locator("#map").click(position={"x": x, "y": y})
    expect(page.locator("#details-body")).to_contain_text("door-1")
    page.mouse.move(box["x"] + x, box["y"] + y)
    page.mouse.down()
    page.mouse.move(box["x"] + x + 5 * scale, box["y"] + y, steps=5)
    page.mouse.move(box["x"] + x + 10 * scale, box["y"] + y, steps=5)
    page.mouse.up()
    expect(page.locator("#message")).to_contain_text("Moved door-1", timeout=10_000)
    moved = httpx.get(f"{demo.base}/v1/buildings/annex/anchors/door-1", headers=op).json()
    assert abs(moved["position"]["x_m"] - 50.0) < 0.5
    assert abs(moved["position"]["y_m"] - 20.0) < 0.5
    assert moved["known"] is True
    assert [
        e for e in watch.console_errors if "422" not in e
    ] == []  # the refused plan's 422, and nothing else
    assert watch.off_loopback == []
    page.context.close()


def test_the_slider_replays_the_crowd_as_it_was(browser: Browser, demo: Demo) -> None:
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(demo.dashboard_link)
    expect(page.locator("#app")).to_have_attribute("data-connection", "connected", timeout=20_000)
    wait_for(lambda: int(root_data(page, "updated-ms")) > 0, 60, "the crowd's first estimates drawn")
    time.sleep(3)  # a few seconds of history
    newest = int(root_data(page, "updated-ms"))
    page.locator("#live-toggle").uncheck()
    page.locator("#history").evaluate(
        "(s) => { s.value = String(Number(s.max) - 2); s.dispatchEvent(new Event('input')); }"
    )
    then = int(page.evaluate("() => window.crowdslamDashboard.history.atMs()"))
    assert newest - 2000 <= then < newest  # two seconds before the newest estimate when Live was turned off
    wait_for(lambda: 0 < int(root_data(page, "updated-ms")) <= then, 10, "the page shows the crowd then")
    expect(page.locator("#status-line")).to_contain_text("replaying")
    listed = httpx.get(
        f"{demo.base}/v1/buildings/demo/positions",
        params={"at_ms": then},
        headers=auth(demo.dashboard_key),
    ).json()
    assert int(root_data(page, "users")) == len(listed) > 0
    assert int(root_data(page, "updated-ms")) == max(e["t_ms"] for e in listed)
    # back to live: the newest estimates again
    page.locator("#live-toggle").check()
    wait_for(lambda: int(root_data(page, "updated-ms")) >= newest, 10, "live again")
    watch.assert_clean()
    page.context.close()


def test_an_operator_draws_a_zone_that_counts_the_crowd_live(browser: Browser, demo: Demo) -> None:
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(f"{demo.base}/dashboard/#key={demo.operator_key}&building={demo.building}")
    expect(page.locator("#app")).to_have_attribute("data-building", demo.building, timeout=20_000)
    page.fill("#zone-name", "Whole floor")
    page.fill("#zone-dwell", "2")
    page.click("#zone-draw")
    for x, y in [(1, 1), (59, 1), (59, 49), (1, 49)]:  # the testbed's floor, 60 x 50 m, corner by corner
        sx, sy = page.evaluate(f"() => window.crowdslamDashboard.view.toScreen({x}, {y})")
        page.locator("#map").click(position={"x": sx, "y": sy})
    page.click("#zone-finish")
    expect(page.locator("#message")).to_contain_text("Saved zone whole-floor", timeout=10_000)
    zones = httpx.get(f"{demo.base}/v1/buildings/demo/zones", headers=auth(demo.dashboard_key)).json()
    [zone] = [z for z in zones if z["id"] == "whole-floor"]
    assert zone["name"] == "Whole floor"
    assert zone["dwell_s"] == 2.0
    ring = zone["polygon"]["coordinates"][0]
    assert len(ring) == 5
    assert all(
        abs(a - b) < 0.5
        for p, q in zip(ring, [(1, 1), (59, 1), (59, 49), (1, 49), (1, 1)], strict=True)
        for a, b in zip(p, q, strict=True)
    )
    # the crowd walks into it: its count on the page rises with the live zone messages, as the API says
    page.wait_for_function(
        "() => /whole-floor:[1-9]/.test(document.querySelector('#app').dataset.zones)", timeout=30_000
    )
    # selected, it shows its figures and its visits
    sx, sy = page.evaluate("() => window.crowdslamDashboard.view.toScreen(30, 3)")
    page.locator("#map").click(position={"x": sx, "y": sy})
    expect(page.locator("#details-body")).to_contain_text("Whole floor")
    expect(page.locator("#details-body")).to_contain_text("visits in the last 24 h", timeout=10_000)
    # and deletes it (the button asks twice)
    page.click("#zone-delete")
    page.click("#zone-delete")
    expect(page.locator("#message")).to_contain_text("Deleted zone whole-floor", timeout=10_000)
    zones = httpx.get(f"{demo.base}/v1/buildings/demo/zones", headers=auth(demo.dashboard_key)).json()
    assert all(z["id"] != "whole-floor" for z in zones)
    watch.assert_clean()
    page.context.close()


def test_an_operator_mints_a_phone_link_whose_qr_code_opens_the_phone_page(
    browser: Browser, demo: Demo
) -> None:
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(f"{demo.base}/dashboard/#key={demo.operator_key}&building={demo.building}")
    expect(page.locator("#tools")).to_be_visible(timeout=20_000)
    page.get_by_text("Phone link", exact=True).click()
    page.locator("#phone-device").fill("phone-visitor")
    page.locator("#phone-mint").click()
    expect(page.locator("#phone-result")).to_be_visible(timeout=10_000)
    link = page.locator("#phone-link").inner_text()
    assert re.fullmatch(rf"{re.escape(demo.base)}/phone/#key=csk_[\w-]+&building=demo", link), link
    # the code on the screen reads back as the link (zxing-cpp, a decoder independent of the page's encoder)
    shot = Image.open(io.BytesIO(page.locator("#phone-qr").screenshot())).convert("L")
    assert [code.text for code in zxingcpp.read_barcodes(np.asarray(shot))] == [link]
    key = parse_qs(urlsplit(link).fragment)["key"][0]
    identity = httpx.get(f"{demo.base}/v1/key", headers=auth(key)).json()
    assert identity == {"scope": "device", "building_id": "demo", "device_id": "phone-visitor"}
    phone = open_page(browser, watch, viewport=(412, 860))
    phone.goto(link)
    expect(phone.locator("#phone")).to_be_visible(timeout=20_000)
    expect(phone.locator("#building-name")).not_to_be_empty()
    watch.assert_clean()
    revoked = httpx.delete(
        f"{demo.base}/v1/buildings/demo/keys/{key.split('_')[1]}", headers=auth(demo.operator_key)
    )
    assert revoked.status_code == 204
