"""A phone with no app, proven without a phone: the page, a real walk's IMU through CDP sensor emulation, the
server, and the estimate back on the page. Both sensor paths (the Generic Sensor API, and DeviceMotion where
it is absent), a network cut that loses nothing and applies nothing twice, and refused permissions."""

from __future__ import annotations

import math
import re
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect
from scipy.spatial.transform import Rotation

from schemas.sensors import TagReading
from server.datasets.msindoor import Trace
from server.datasets.msindoor_batches import trace_batches
from server.recordings.recorder import RecordedBatch
from server.replay import replay_offline
from server.settings import Settings
from tests.server.dashboard.conftest import Watch, open_page, wait_for
from tests.server.phone.conftest import PhoneServer, SensorPlayer

NO_GENERIC_SENSORS = """
for (const name of ["Accelerometer", "Gyroscope", "AbsoluteOrientationSensor", "RelativeOrientationSensor",
  "Magnetometer", "LinearAccelerationSensor", "GravitySensor"]) delete window[name];
"""


def data(page: Page, name: str) -> str:
    return page.locator("#app").get_attribute(f"data-{name}") or ""


def replayed_steps(walk: Trace) -> int:
    """What ``crowdslam replay --offline`` counts on the same walk, posted as the server's importer does."""
    batches = [
        RecordedBatch(i, b.model_dump_json(exclude_none=True).encode())
        for i, b in enumerate(trace_batches(walk, "replayed", "walk"))
    ]
    with tempfile.TemporaryDirectory() as folder:
        report = replay_offline(batches, Settings(data_dir=Path(folder)))
    return report.steps


def open_phone(browser: Browser, server: PhoneServer, building: str, device: str, watch: Watch) -> Page:
    key = server.device_key(building, device)
    page = open_page(browser, watch, viewport=(412, 860))
    page.context.grant_permissions(["accelerometer", "gyroscope", "magnetometer"], origin=server.base)
    page.goto(f"{server.base}/phone/#key={key}&building={building}")
    expect(page.locator("#app")).to_have_attribute("data-ready", "true", timeout=20_000)
    assert "key=" not in page.url  # the key left the address bar at once
    expect(page.locator("#placement")).to_contain_text("Not placed yet")
    return page


def tap_here(page: Page, x_m: float, y_m: float) -> float:
    """'I am here', the plan zoomed in where the walk starts (as a person does to tap their place), then a
    tap there; the fix's sigma as the page says it."""
    box = page.locator("#map").bounding_box()
    assert box is not None
    px, py = page.evaluate(f"window.crowdslamPhone.view.toScreen({x_m}, {y_m})")
    page.mouse.move(box["x"] + px, box["y"] + py)
    for _ in range(10):
        page.mouse.wheel(0, -100)
    page.locator("#here").click()
    px, py = page.evaluate(f"window.crowdslamPhone.view.toScreen({x_m}, {y_m})")
    page.mouse.click(box["x"] + px, box["y"] + py)
    expect(page.locator("#message")).to_contain_text("goes to the server")
    said = re.search(r"within ([\d.]+) m", page.locator("#message").inner_text())
    assert said is not None
    return float(said.group(1))


def own_history(server: PhoneServer, building: str, device: str) -> list[dict[str, object]]:
    response = httpx.get(
        f"{server.base}/v1/buildings/{building}/users/{device}/positions",
        headers=server.auth(server.operator),
    )
    assert response.status_code == 200, response.text
    return list(response.json())


def test_a_walk_through_the_generic_sensor_api_is_tracked_and_a_network_cut_loses_nothing(
    browser: Browser, phone_server: PhoneServer, walk: Trace, tmp_path: Path
) -> None:
    server, building, device = phone_server, "mall-generic", "phone-generic"
    server.building(building)
    watch = Watch()
    page = open_phone(browser, server, building, device, watch)
    player = SensorPlayer(page, walk)
    start = walk.waypoints[0]
    sigma = tap_here(page, float(start[1]), float(start[2]))
    assert 2.0 <= sigma <= 4.0  # a finger's 20 px on the zoomed plan
    page.locator("#start").click()
    expect(page.locator("#app")).to_have_attribute("data-state", "running", timeout=10_000)
    assert data(page, "mode") == "generic"
    expect(page.locator('#sensors li[data-sensor="accelerometer"]')).to_have_attribute("data-state", "ok")
    expect(page.locator('#sensors li[data-sensor="orientation"]')).to_have_attribute("data-state", "ok")

    offline_seen: list[str] = []

    def cut() -> None:
        page.route("**/v1/buildings/*/batches", lambda route: route.abort("internetdisconnected"))

    def during_cut() -> None:
        offline_seen.append(page.locator("#link").get_attribute("data-state") or "")
        offline_seen.append(data(page, "queued"))

    def restore() -> None:
        page.unroute("**/v1/buildings/*/batches")

    # the network is cut from 3 s to 13 s into the walk: ten batches wait in the page, then go in order
    player.play(during=[(3.0, cut), (12.0, during_cut), (13.0, restore)])
    page.locator("#stop").click()
    wait_for(lambda: data(page, "queued") == "0" and data(page, "state") == "idle", 60, "every batch sent")
    assert offline_seen[0] == "offline", offline_seen
    assert int(offline_seen[1]) >= 5, offline_seen

    # nothing lost, nothing applied twice: every batch the page sealed was applied once, in order
    sealed = page.evaluate("window.crowdslamPhone.outbox.seq")
    assert data(page, "lost") == "0"
    assert data(page, "refused") == "0"
    assert data(page, "late") == "0"
    assert int(data(page, "applied")) == sealed
    assert server.counter("batches", building) == sealed
    assert server.counter("late", building) == 0
    history = own_history(server, building, device)
    times = [int(e["t_ms"]) for e in history]  # type: ignore[call-overload]
    assert times == sorted(set(times)), "an estimate was published twice"

    # the steps the server counted from the page's samples are the replayed walk's, within 10 %
    expected = replayed_steps(walk)
    counted = server.counter("steps_detected", building)
    assert abs(counted - expected) <= 0.1 * expected, (counted, expected)

    # the estimate moved along the walk, ended near its end, and the page shows it with its ring
    positions = np.array([[e["position"]["x_m"], e["position"]["y_m"]] for e in history])  # type: ignore[index]
    travelled = float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())
    walked = float(np.linalg.norm(np.diff(walk.waypoints[:, 1:], axis=0), axis=1).sum())
    assert travelled > 0.5 * walked, (travelled, walked)
    latest = httpx.get(
        f"{server.base}/v1/buildings/{building}/devices/{device}/position",
        headers=server.auth(server.operator),
    ).json()["estimate"]
    final = (latest["position"]["x_m"], latest["position"]["y_m"])
    error = math.dist(final, walk.waypoints[-1, 1:])
    # measured 2.1 m on a 17.7 m walk (the same walk replayed offline from an exact start: 1.3 m)
    assert error < 5.0, (final, walk.waypoints[-1], walked)
    expect(page.locator("#app")).to_have_attribute("data-placed", "true")
    expect(page.locator("#placement")).to_contain_text("95 %")
    assert math.isclose(float(data(page, "x")), final[0], abs_tol=0.01)
    assert math.isclose(float(data(page, "y")), final[1], abs_tol=0.01)
    per_minute = page.evaluate("window.crowdslamPhone.outbox.bytesPerMinute()") / 1024
    assert per_minute < 150  # gzip-compressed: ~90 KiB a minute (the raw JSON is ~320)
    print(
        f"phone page: {sealed} batches, {counted:.0f} steps (replay {expected}), travelled {travelled:.1f} m "
        f"of {walked:.1f} m, final error {error:.1f} m, {per_minute:.0f} KiB a minute"
    )
    page.screenshot(path=str(tmp_path / "phone.png"))
    # the only errors the page logged are the posts the cut refused
    cut_errors = [e for e in watch.console_errors if "ERR_INTERNET_DISCONNECTED" in e]
    assert cut_errors, "the cut was not seen"
    watch.console_errors = [e for e in watch.console_errors if e not in cut_errors]
    watch.assert_clean()


def test_a_walk_through_devicemotion_where_the_generic_sensor_api_is_absent(
    browser: Browser, phone_server: PhoneServer, walk: Trace
) -> None:
    server, building, device = phone_server, "mall-events", "phone-events"
    server.building(building)
    watch = Watch()
    key = server.device_key(building, device)
    page = open_page(browser, watch, viewport=(412, 860))
    page.add_init_script(NO_GENERIC_SENSORS)
    page.context.grant_permissions(["accelerometer", "gyroscope", "magnetometer"], origin=server.base)
    page.goto(f"{server.base}/phone/#key={key}&building={building}")
    expect(page.locator("#app")).to_have_attribute("data-ready", "true", timeout=20_000)
    player = SensorPlayer(page, walk, events=True)
    start = walk.waypoints[0]
    tap_here(page, float(start[1]), float(start[2]))
    page.locator("#start").click()
    expect(page.locator("#app")).to_have_attribute("data-state", "running", timeout=10_000)
    assert data(page, "mode") == "events"
    player.play()
    page.locator("#stop").click()
    wait_for(lambda: data(page, "queued") == "0" and data(page, "state") == "idle", 60, "every batch sent")
    expected = replayed_steps(walk)
    counted = server.counter("steps_detected", building)
    assert abs(counted - expected) <= 0.1 * expected, (counted, expected)
    expect(page.locator("#app")).to_have_attribute("data-placed", "true")
    watch.assert_clean()


@pytest.mark.parametrize("platform", ["ios", "chrome"])
def test_refused_motion_access_says_what_it_costs(
    browser: Browser, phone_server: PhoneServer, platform: str
) -> None:
    """The page asks on a tap (``DeviceMotionEvent.requestPermission``: iOS, and this Chromium too), refused
    by iOS's dialog or by the site's motion permission blocked in Chrome: the refusal is said with its cost,
    and nothing is sent."""
    server, building = phone_server, f"mall-refused-{platform}"
    server.building(building)
    watch = Watch()
    key = server.device_key(building, f"phone-refused-{platform}")
    page = open_page(browser, watch, viewport=(412, 860))
    if platform == "ios":
        page.add_init_script(
            NO_GENERIC_SENSORS + "DeviceMotionEvent.requestPermission = async () => 'denied';"
        )
    else:
        cdp = page.context.new_cdp_session(page)
        context_id = cdp.send("Target.getTargetInfo")["targetInfo"]["browserContextId"]
        for kind in ("accelerometer", "gyroscope", "absolute-orientation", "linear-acceleration", "gravity"):
            cdp.send("Emulation.setSensorOverrideEnabled", {"enabled": True, "type": kind})
        browser_cdp = browser.new_browser_cdp_session()
        for name in ("accelerometer", "gyroscope", "magnetometer"):
            browser_cdp.send(
                "Browser.setPermission",
                {
                    "permission": {"name": name},
                    "setting": "denied",
                    "origin": server.base,
                    "browserContextId": context_id,
                },
            )
    page.goto(f"{server.base}/phone/#key={key}&building={building}")
    expect(page.locator("#app")).to_have_attribute("data-ready", "true", timeout=20_000)
    page.locator("#start").click()
    expect(page.locator("#message")).to_contain_text("Motion sensors were refused", timeout=10_000)
    expect(page.locator("#message")).to_contain_text("cannot count your steps")
    assert data(page, "state") == "refused"
    accelerometer = page.locator('#sensors li[data-sensor="accelerometer"]')
    expect(accelerometer).to_have_attribute("data-state", "refused")
    expect(accelerometer).to_contain_text("without it the server cannot follow this phone")
    time.sleep(1.5)
    assert data(page, "sent") == "0"
    watch.assert_clean()


def test_the_page_keeps_only_the_key_and_forgets_it_on_request(
    browser: Browser, phone_server: PhoneServer
) -> None:
    server, building = phone_server, "mall-forget"
    server.building(building)
    watch = Watch()
    page = open_phone(browser, server, building, "phone-forget", watch)
    stored = page.evaluate("Object.keys(localStorage)")
    assert stored == ["crowdslam.phone"]
    page.reload()  # the stored key opens the page again, without the link
    expect(page.locator("#phone")).to_be_visible(timeout=20_000)
    page.get_by_text("This phone", exact=True).click()
    page.locator("#forget").click()
    expect(page.locator("#forget")).to_have_text("Tap again to forget")
    page.locator("#forget").click()
    expect(page.locator("#welcome")).to_be_visible()
    assert page.evaluate("localStorage.length") == 0
    watch.assert_clean()


def test_a_tags_qr_code_becomes_a_tag_reading_or_is_refused_saying_why(
    browser: Browser, phone_server: PhoneServer
) -> None:
    """What ``BarcodeDetector`` reads (headless Chromium has no camera): the page's own conversion."""
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(f"{phone_server.base}/phone/")
    expect(page.locator("#welcome")).to_be_visible(timeout=20_000)
    readings = page.evaluate(
        """async () => {
          const { tagReading } = await import("/phone/assets/tags.js");
          return ["#6e1ebc 40.684492,-74.401406 z1", "lobby-north", "https://example.com/x", "# bad"]
            .map((text) => tagReading(text, 1796559880000.4));
        }"""
    )
    assert readings[0] == [
        {
            "kind": "tag",
            "t_ms": 1796559880000,
            "tag_id": "6e1ebc",
            "payload": "#6e1ebc 40.684492,-74.401406 z1",
        },
        "",
    ]
    assert readings[1] == [{"kind": "tag", "t_ms": 1796559880000, "tag_id": "lobby-north"}, ""]
    assert readings[2] == [None, "this QR code is not a building tag"]
    assert readings[3][0] is None
    # each reading the page makes is one the server's contract accepts
    TagReading.model_validate(readings[0][0])
    TagReading.model_validate(readings[1][0])
    watch.assert_clean()


def test_the_pages_sensor_conversions_match_their_oracles(
    browser: Browser, phone_server: PhoneServer
) -> None:
    """W3C's Z-X'-Y'' Euler angles as a quaternion (scipy's intrinsic ZXY as the oracle), and the 50 Hz cap on
    a 60 Hz stream with strictly increasing integer times."""
    watch = Watch()
    page = open_page(browser, watch)
    page.goto(f"{phone_server.base}/phone/")
    expect(page.locator("#welcome")).to_be_visible(timeout=20_000)
    rng = np.random.default_rng(0)
    angles = np.column_stack([rng.uniform(0, 360, 50), rng.uniform(-180, 180, 50), rng.uniform(-90, 90, 50)])
    got = np.array(
        page.evaluate(
            """async (angles) => {
              const { quaternionFromEuler } = await import("/phone/assets/sensors.js");
              return angles.map(([a, b, g]) => quaternionFromEuler(a, b, g));
            }""",
            angles.tolist(),
        )
    )
    expected = Rotation.from_euler("ZXY", angles, degrees=True).as_quat()  # x, y, z, w
    same_sign = np.sign(np.sum(got * expected, axis=1))[:, None]  # q and -q are one rotation
    np.testing.assert_allclose(got, expected * same_sign, atol=1e-12)

    kept = page.evaluate(
        """async () => {
          const { Stream } = await import("/phone/assets/sensors.js");
          const s = new Stream(["x"]);
          for (let i = 0; i < 600; i++) s.push(1796559880000 + i * 1000 / 60 + (i % 3) * 0.4, [i], 3);
          s.push(1796559880000 + 599 * 1000 / 60, [0], 3);  // a repeated time: dropped
          return s.take().t_ms;
        }"""
    )
    t = np.array(kept)
    assert np.all(np.diff(t) > 0)
    rate = (len(t) - 1) / ((t[-1] - t[0]) / 1000)
    assert 45 <= rate <= 50.5, rate
    watch.assert_clean()


def test_the_floor_picker_shows_each_floor_and_a_tap_says_its_floor(
    browser: Browser, phone_server: PhoneServer
) -> None:
    server, building = phone_server, "mall-floors"
    server.building(building, upper_floors=2)
    watch = Watch()
    page = open_phone(browser, server, building, "phone-floors", watch)
    assert page.locator("#floor option").all_inner_texts() == ["F1 (0)", "F2 (1)", "F3 (2)"]
    assert page.evaluate("window.crowdslamPhone.scene.plan !== null")  # the ground floor has its plan
    page.locator("#floor").select_option("1")
    wait_for(lambda: page.evaluate("window.crowdslamPhone.scene.floor") == 1, 10, "floor 1 shown")
    assert page.evaluate("window.crowdslamPhone.scene.plan === null")  # no plan there: its extent
    tap_here(page, 100.0, 80.0)
    fix = page.evaluate("window.crowdslamPhone.landmarks[0]")
    assert fix["kind"] == "fix"
    assert fix["floor"] == 1
    assert abs(fix["position"]["x_m"] - 100.0) < 0.5
    assert abs(fix["position"]["y_m"] - 80.0) < 0.5
    # tapped two minutes before Start, the place is sent timed within its batch (whose span is bounded)
    sent_ms, now_ms = page.evaluate(
        """() => {
          const phone = window.crowdslamPhone;
          phone.landmarks[0].t_ms -= 120000;
          return [phone.takeBatch().landmarks[0].t_ms, Date.now()];
        }"""
    )
    assert now_ms - 1500 <= sent_ms <= now_ms
    watch.assert_clean()


def test_a_revoked_key_stops_the_page_and_is_forgotten(
    browser: Browser, phone_server: PhoneServer, walk: Trace
) -> None:
    """Revoked while sending: the page stops and says so. Loaded again: the dead key is dropped."""
    server, building = phone_server, "mall-revoked"
    server.building(building)
    watch = Watch()
    key = server.device_key(building, "phone-revoked")
    page = open_page(browser, watch, viewport=(412, 860))
    page.context.grant_permissions(["accelerometer", "gyroscope", "magnetometer"], origin=server.base)
    page.goto(f"{server.base}/phone/#key={key}&building={building}")
    expect(page.locator("#app")).to_have_attribute("data-ready", "true", timeout=20_000)
    player = SensorPlayer(page, walk)
    page.locator("#start").click()
    expect(page.locator("#app")).to_have_attribute("data-state", "running", timeout=10_000)
    player.play(until_s=3.0)  # a few batches first
    revoked = httpx.delete(
        f"{server.base}/v1/buildings/{building}/keys/{key.split('_')[1]}",
        headers=server.auth(server.operator),
    )
    assert revoked.status_code == 204
    player.play(until_s=3.0)  # the walk again: the next batch meets the revocation
    expect(page.locator("#app")).to_have_attribute("data-state", "refused", timeout=10_000)
    expect(page.locator("#message")).to_contain_text("refuses this phone's key")
    page.reload()
    expect(page.locator("#welcome-message")).to_contain_text("unknown or revoked", timeout=20_000)
    assert page.evaluate("localStorage.length") == 0
    # the refused requests are the only errors the page logged
    watch.console_errors = [e for e in watch.console_errors if "401" not in e]
    watch.assert_clean()
