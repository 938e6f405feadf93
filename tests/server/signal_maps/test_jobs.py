"""Signal-map builds through the API: recordings in, a SignalSLAM build in its own process, files out."""

from __future__ import annotations

import json
import math
import time
from typing import Any

from slam_core.crowd.fingerprints import SURVEY_OWNER
from tests.server.conftest import Api

T0 = 1_767_225_600_000
APS = [f"0a:00:00:00:00:{i:02x}" for i in range(8)]


def _walk(
    device: str,
    x0: float,
    x1: float,
    seconds: int,
    with_end_fix: bool = True,
    floors: tuple[int, int] = (0, 0),
) -> list[dict[str, Any]]:
    """A phone walking along y = 0 from x0 to x1, posting one batch a second: steps with azimuths, a WiFi
    scan every 2 s whose RSS falls with the distance to 8 APs along the corridor, fixes at both ends (on
    ``floors``)."""
    azimuth = math.pi / 2 if x1 > x0 else -math.pi / 2
    step = (x1 - x0) / (2 * seconds)
    batches = []
    for s in range(seconds):
        t = T0 + 1000 * s
        body: dict[str, Any] = {
            "building_id": "hq",
            "device_id": device,
            "batch_id": f"{device}-{s}",
            "seq": s,
            "steps": [
                {"t_ms": t + 250 + 500 * k, "length_m": abs(step), "azimuth_rad": azimuth} for k in range(2)
            ],
        }
        x = x0 + step * 2 * s
        # LTE: two cells, RSRP falling away from each end; the magnetic magnitude rises along the corridor
        body["lte"] = [
            {"t_ms": t + 200, "cell_id": "310-410-1", "rsrp_dbm": round(-70.0 - 1.0 * x, 1)},
            {"t_ms": t + 200, "cell_id": "310-410-2", "rsrp_dbm": round(-98.0 + 1.0 * x, 1)},
        ]
        ts = [t + 100 * k for k in range(10)]
        body["magnetometer"] = {"t_ms": ts, "x": [20.0 + x] * 10, "y": [10.0] * 10, "z": [-35.0] * 10}
        if s % 2 == 0:
            heard = [(b, round(-35.0 - 2.0 * abs(x - 4.0 * i), 1)) for i, b in enumerate(APS)]
            aps = [{"bssid": b, "rssi_dbm": r, "frequency_mhz": 2412} for b, r in heard if r > -90]
            body["wifi_scans"] = [{"t_ms": t + 100, "aps": aps}]
        marks = []
        if s == 0:
            marks.append(
                {
                    "kind": "fix",
                    "t_ms": t,
                    "position": {"x_m": x0, "y_m": 0.0},
                    "sigma_m": 0.5,
                    "floor": floors[0],
                }
            )
        if s == seconds - 1 and with_end_fix:
            marks.append(
                {
                    "kind": "fix",
                    "t_ms": t + 999,
                    "position": {"x_m": x1, "y_m": 0.0},
                    "sigma_m": 0.5,
                    "floor": floors[1],
                }
            )
        if marks:
            body["landmarks"] = marks
        batches.append(body)
    return batches


def _post(api: Api, batches: list[dict[str, Any]], device: str) -> None:
    key = api.key("hq", "device", device)
    for body in batches:
        r = api.client.post("/v1/buildings/hq/batches", json=body, headers=api.auth(key))
        assert r.status_code == 200, r.text


def _wait(api: Api, job_id: str, timeout_s: float = 120.0) -> dict[str, Any]:
    op = api.auth(api.operator)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = api.client.get(f"/v1/buildings/hq/signal-maps/{job_id}", headers=op).json()
        if job["status"] in ("done", "failed"):
            return dict(job)
        time.sleep(0.2)
    raise AssertionError(f"build {job_id} did not finish in {timeout_s} s")


def test_a_build_from_recordings_serves_maps(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building(geo=True)
    op = api.auth(api.operator)
    assert api.client.post("/v1/buildings/hq/signal-maps", headers=op).status_code == 409  # nothing recorded
    _post(api, _walk("phone-a", 0.0, 28.0, 20), "phone-a")
    _post(api, _walk("phone-b", 28.0, 0.0, 20), "phone-b")
    started = api.client.post("/v1/buildings/hq/signal-maps", headers=op)
    assert started.status_code == 202, started.text
    assert started.json()["status"] == "queued"
    assert started.json()["recordings"] >= 1
    job = _wait(api, started.json()["id"])
    assert job["status"] == "done", job
    assert job["segments"] == 2
    assert job["devices"] == 2
    assert job["access_points"] == len(APS)
    assert {"trajectories.json", "fingerprints_5m.json", "signal_map_ap1.json", "signal_map_ap1.png"} <= set(
        job["files"]
    )
    # LTE cells and the magnetic magnitude are mapped too, whatever the signal edges used
    assert {"signal_map_cell1.json", "signal_map_cell2.png", "signal_map_magnetic1.json"} <= set(job["files"])
    base = f"/v1/buildings/hq/signal-maps/{job['id']}/files"
    tracks = api.client.get(f"{base}/trajectories.json", headers=op)
    assert tracks.status_code == 200
    for track in tracks.json():
        xy = track["xy_m"]
        assert max(abs(float(p[1])) for p in xy) < 1.0  # stays in the corridor
        assert abs(abs(xy[-1][0] - xy[0][0]) - 28.0) < 1.5
    png = api.client.get(f"{base}/signal_map_ap1.png", headers=op)
    assert png.status_code == 200
    assert png.headers["content-type"] == "image/png"
    grid = json.loads(api.client.get(f"{base}/signal_map_ap1.json", headers=op).content)
    assert grid["bssid"] in APS
    geo = api.client.get(
        f"{base}/signal_map_ap1.geojson", headers=op
    ).json()  # the building is geo-referenced
    assert geo["type"] == "FeatureCollection"
    assert len(geo["features"]) > 10
    lon, lat = geo["features"][0]["geometry"]["coordinates"]
    assert -90 <= lat <= 90
    assert -180 <= lon <= 180
    cell = json.loads(api.client.get(f"{base}/signal_map_cell1.json", headers=op).content)
    assert cell["cell_id"] in ("310-410-1", "310-410-2")
    magnetic = json.loads(api.client.get(f"{base}/signal_map_magnetic1.json", headers=op).content)
    means = [v for row in magnetic["mean_ut"] for v in row if v is not None]
    assert 35.0 < min(means) < max(means) < 65.0  # |(20 + x, 10, -35)| over x in [0, 28]
    listed = api.client.get("/v1/buildings/hq/signal-maps", headers=op).json()
    assert [j["id"] for j in listed] == [job["id"]]
    # the build's radio map: every scan at its SignalSLAM position, loaded into the building's fingerprints
    radio = json.loads(api.client.get(f"{base}/radio_map.json", headers=op).content)["scans"]
    assert len(radio) == 20  # a scan every 2 s of two 20 s walks
    assert all(abs(s["y_m"]) < 1.0 and set(s["aps"]) <= set(APS) for s in radio)
    tracker: Any = api.client.app.state.crowdslam.tracking.handles["hq"].host.tracker  # type: ignore[attr-defined]
    deadline = time.monotonic() + 10
    while tracker.radio_map_id != job["id"] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert tracker.radio_map_id == job["id"]
    assert (
        tracker.fingerprints.map_of(0)._per_owner[SURVEY_OWNER] >= 5
    )  # at most 4 a 4 m cell: the 28 m corridor


def test_each_floor_gets_its_own_maps_and_its_scans_join_its_fingerprints(sqlite_api: Api) -> None:
    api = sqlite_api
    op = api.auth(api.operator)
    floors = [{"level": 0, "name": "Ground"}, {"level": 1, "name": "First"}]
    created = api.client.post("/v1/buildings", json={"id": "hq", "name": "HQ", "floors": floors}, headers=op)
    assert created.status_code == 201, created.text
    _post(api, _walk("phone-a", 0.0, 28.0, 20), "phone-a")
    _post(api, _walk("phone-b", 28.0, 0.0, 20, floors=(1, 1)), "phone-b")
    _post(api, _walk("phone-c", 0.0, 28.0, 20, floors=(0, 1)), "phone-c")  # fixes on two floors: left out
    job = _wait(api, api.client.post("/v1/buildings/hq/signal-maps", headers=op).json()["id"])
    assert job["status"] == "done", job
    assert (job["floors"], job["segments"], job["segments_across_floors"]) == ([0, 1], 2, 1)
    for level in (0, 1):
        assert {f"floor{level}_signal_map_ap1.json", f"floor{level}_fingerprints_5m.json"} <= set(
            job["files"]
        )
    assert "signal_map_ap1.json" not in job["files"]
    base = f"/v1/buildings/hq/signal-maps/{job['id']}/files"
    tracks = api.client.get(f"{base}/trajectories.json", headers=op).json()
    assert sorted((t["device_id"], t["floor"]) for t in tracks) == [("phone-a", 0), ("phone-b", 1)]
    radio = json.loads(api.client.get(f"{base}/radio_map.json", headers=op).content)["scans"]
    assert sorted({s["floor"] for s in radio}) == [0, 1]
    tracker: Any = api.client.app.state.crowdslam.tracking.handles["hq"].host.tracker  # type: ignore[attr-defined]
    deadline = time.monotonic() + 10
    while tracker.radio_map_id != job["id"] and time.monotonic() < deadline:
        time.sleep(0.05)
    for level in (0, 1):
        assert tracker.fingerprints.map_of(level)._per_owner[SURVEY_OWNER] >= 5


def test_build_errors(sqlite_api: Api) -> None:
    api = sqlite_api
    api.create_building()
    op = api.auth(api.operator)
    _post(api, _walk("phone-c", 0.0, 10.0, 8, with_end_fix=False), "phone-c")  # one landmark only
    job = _wait(api, api.client.post("/v1/buildings/hq/signal-maps", headers=op).json()["id"])
    assert job["status"] == "failed"
    assert "between two landmarks" in job["error"]
    assert api.client.get("/v1/buildings/hq/signal-maps/nope", headers=op).status_code == 404
    missing = api.client.get(f"/v1/buildings/hq/signal-maps/{job['id']}/files/x.png", headers=op)
    assert missing.status_code == 404
    assert missing.json()["status"] == 404
    dashboard = api.auth(api.key("hq", "dashboard"))
    assert api.client.post("/v1/buildings/hq/signal-maps", headers=dashboard).status_code == 403
    assert api.client.get("/v1/buildings/nowhere/signal-maps", headers=op).status_code in (403, 404)


def test_queued_builds_say_so_and_the_queue_is_bounded(sqlite_api: Api) -> None:
    """Builds run one at a time: the others are reported queued, not running (the pool takes the next job
    off its queue before it starts it); past ``MAX_PENDING_BUILDS`` a new one is refused with 429."""
    from server.signal_maps.jobs import MAX_PENDING_BUILDS

    api = sqlite_api
    api.create_building()
    op = api.auth(api.operator)
    _post(api, _walk("phone-a", 0.0, 28.0, 20), "phone-a")
    started = [api.client.post("/v1/buildings/hq/signal-maps", headers=op) for _ in range(MAX_PENDING_BUILDS)]
    assert all(r.status_code == 202 for r in started)
    refused = api.client.post("/v1/buildings/hq/signal-maps", headers=op)
    assert refused.status_code == 429
    assert int(refused.headers["retry-after"]) >= 1
    seen_running = 0
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        statuses = [j["status"] for j in api.client.get("/v1/buildings/hq/signal-maps", headers=op).json()]
        assert statuses.count("running") <= 1, statuses
        seen_running = max(seen_running, statuses.count("running"))
        if all(s in ("done", "failed") for s in statuses):
            break
        time.sleep(0.05)
    assert all(s == "done" for s in statuses), statuses
    assert seen_running == 1
    assert api.client.post("/v1/buildings/hq/signal-maps", headers=op).status_code == 202  # room again
