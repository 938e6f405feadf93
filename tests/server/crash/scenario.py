"""The crash-anywhere scenario: a building of three floors without a floor 0, a crowd walking it and its
operators at work, as a fixed list of requests.

Built from the simulated world of three storeys (``server/data/three-floors.json``, its floors numbered 1 to
3 here), five phones:
- phone 0 starts with a reading of a lift pinned where it stands, on floor 3;
- phone 1 starts at a tag whose payload encodes its place and floor (``z3``), and has no barometer: its
  phone reports the rise when it changes floors;
- phones 2 and 3 start with a fix and meet another halfway (the signal-map build's walks between two
  landmarks), phone 4 with a fix; the others' barometers tell their changes of floor;
- operators pin the world's known anchors (on every floor) before the crowd walks, then, while it walks,
  pin an anchor, move it, upload a floor plan, pin two anchors and merge them, delete the first, draw a
  zone and delete another (the crowd's visits to zones drawn beforehand), build a signal map that the
  building loads, forget phone 4's user and revoke its key.

Every request is posted one after another (a phone's next batch once the last is answered), so every batch
is an tracker call of its own, and the run has one outcome: a crash anywhere must not change it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from schemas.common import Position
from schemas.floor_plans import FLOOR_PLAN_EXAMPLE
from schemas.sensors import AnchorReading, PositionFix, SensorBatch, TagReading
from server.simulation.phones import EPOCH_MS, device_id, known_anchors, simulated_batches
from slam_core.geo import GeoFrame
from slam_core.sim.simulation import Scenario, Simulation, simulate
from tests.conftest import ROOT

BUILDING = "hq"
FLOOR_OFFSET = 1
"""The simulated world's floors are 0-2; the building's are 1-3 (it has no floor 0)."""
GEO = GeoFrame(48.137, 11.575, 0.2)
USERS = 5
WORLD_SEED = 1
"""A world whose walks change floors: by barometer, and by a phone without one that reports the rise."""
FORGOTTEN = device_id(4)


@dataclass(frozen=True)
class Step:
    """One request of the scenario: a phone's batch, or an operator's call."""

    name: str
    method: str
    path: str
    key: str
    """Whose key: ``operator`` or a device id."""
    body: Any = None
    batch: SensorBatch | None = None
    again: frozenset[int] = frozenset()
    """Statuses that say a request sent again after a crash had taken effect before it (404 for a delete
    that had deleted)."""
    killable: bool = True
    """Whether a crash may fall in it (a signal-map build is a process a crash fails: started again)."""

    @property
    def ok(self) -> frozenset[int]:
        return frozenset({200, 201, 202, 204})


@dataclass
class CrashScenario:
    sim: Simulation
    setup: list[Step]
    """Before the crowd walks (no crash falls in them): the building, its known anchors."""
    steps: list[Step]
    devices: list[str]
    revoked: str = FORGOTTEN
    """The device whose key the scenario revokes (a step named ``revoke``)."""
    batches: dict[str, SensorBatch] = field(default_factory=dict)
    """Every batch posted, by batch id."""

    @property
    def killable(self) -> list[int]:
        return [i for i, s in enumerate(self.steps) if s.killable]


def _world() -> Simulation:
    raw = json.loads((ROOT / "server" / "data" / "three-floors.json").read_text())
    raw["users"]["count"] = USERS
    raw["users"]["walk_length_m"] = 70.0
    return simulate(Scenario.from_dict(raw), WORLD_SEED)


def _shifted(batch: SensorBatch) -> SensorBatch:
    marks = [
        m.model_copy(update={"floor": m.floor + FLOOR_OFFSET}) if isinstance(m, PositionFix) else m
        for m in batch.landmarks
    ]
    return batch.model_copy(update={"landmarks": marks})


def _anchor(kind: str, x: float, y: float, floor: int, label: str | None = None) -> dict[str, Any]:
    body: dict[str, Any] = {"type": kind, "position": {"x_m": x, "y_m": y}, "floor": floor}
    if label is not None:
        body["label"] = label
    return body


def crash_scenario() -> CrashScenario:
    sim = _world()
    floor = sim.scenario["floor"]
    devices = [device_id(u) for u in range(USERS)]
    building = {
        "id": BUILDING,
        "name": "Three floors, none of them 0",
        "floors": [
            {"level": lv + FLOOR_OFFSET, "name": f"F{lv + FLOOR_OFFSET}", **_size(floor)}
            for lv in range(sim.world.levels)
        ],
        "geo_reference": {
            "origin_lat_deg": GEO.origin_lat_deg,
            "origin_lon_deg": GEO.origin_lon_deg,
            "rotation_rad": GEO.rotation_rad,
        },
    }
    setup = [Step("create the building", "POST", "/v1/buildings", "operator", building)]
    for k, anchor in enumerate(known_anchors(sim)):
        x, y = anchor.position
        body = _anchor(anchor.type.value, x, y, anchor.level + FLOOR_OFFSET)
        setup.append(
            Step(f"pin known-{k}", "PUT", f"/v1/buildings/{BUILDING}/anchors/known-{k}", "operator", body)
        )

    # a zone where each phone is halfway through its walk (visits to keep over the crashes)
    zones = f"/v1/buildings/{BUILDING}/zones"
    for u in range(USERS):
        setup.append(Step(f"draw zone-{u}", "PUT", f"{zones}/zone-{u}", "operator", _zone(sim, u, 0.5)))

    batches = [_shifted(b) for b in simulated_batches(sim, BUILDING)]
    firsts = {d: next(b for b in batches if b.device_id == d) for d in devices}
    # phone 0: a lift pinned where it starts, read instead of a fix
    start = firsts[devices[0]].landmarks[0]
    assert isinstance(start, PositionFix)
    lift = _anchor("elevator", start.position.x_m, start.position.y_m, start.floor, "the lift")
    setup.append(
        Step("pin the lift", "PUT", f"/v1/buildings/{BUILDING}/anchors/lift-start", "operator", lift)
    )
    reading = AnchorReading(t_ms=start.t_ms, anchor_id="lift-start")
    # phone 1: a tag encoding its place and floor
    start1 = firsts[devices[1]].landmarks[0]
    assert isinstance(start1, PositionFix)
    lat, lon = GEO.to_wgs84(start1.position.x_m, start1.position.y_m)
    tag = TagReading(t_ms=start1.t_ms, tag_id="tag-1", payload=f"#tag1 {lat:.8f},{lon:.8f} z{start1.floor}")
    # phones 2 and 3: a fix again halfway (a walk between two landmarks for the signal-map build)
    halfway = {}
    for d in devices[2:4]:
        mine = [b for b in batches if b.device_id == d]
        there = next(b for b in mine[len(mine) // 2 :] if b.steps)
        halfway[there.batch_id] = _true_fix(sim, devices.index(d), there)
    rises = _rises(sim, 1)
    walked: list[SensorBatch] = []
    for b in batches:
        if b.device_id == devices[1] and any(d.type.value in rises for d in b.anchor_detections):
            marked = [
                d.model_copy(update={"rise_m": rises[d.type.value]}) if d.type.value in rises else d
                for d in b.anchor_detections
            ]
            b = b.model_copy(update={"anchor_detections": marked})
        if b.batch_id == firsts[devices[0]].batch_id:
            b = b.model_copy(update={"landmarks": [reading]})
        elif b.batch_id == firsts[devices[1]].batch_id:
            b = b.model_copy(update={"landmarks": [tag]})
        elif b.batch_id in halfway:
            b = b.model_copy(update={"landmarks": [*b.landmarks, halfway[b.batch_id]]})
        walked.append(b)

    n = len(walked)
    edits: dict[int, list[Step]] = {}

    def at(share: float, *steps: Step) -> None:
        edits.setdefault(int(share * n), []).extend(steps)

    anchors = f"/v1/buildings/{BUILDING}/anchors"
    plan = {**FLOOR_PLAN_EXAMPLE, "features": FLOOR_PLAN_EXAMPLE["features"][:2]}
    at(
        0.15,
        Step("pin the kiosk", "PUT", f"{anchors}/kiosk", "operator", _anchor("door", 12.0, 8.0, 2, "kiosk")),
    )
    at(
        0.25,
        Step("move the kiosk", "PUT", f"{anchors}/kiosk", "operator", _anchor("door", 14.0, 8.0, 2, "kiosk")),
    )
    at(
        0.30,
        Step("upload floor 2's plan", "PUT", f"/v1/buildings/{BUILDING}/floors/2/plan", "operator", plan),
    )
    at(
        0.40,
        Step("pin dup-a", "PUT", f"{anchors}/dup-a", "operator", _anchor("stairs", 30.0, 20.0, 3)),
        Step("pin dup-b", "PUT", f"{anchors}/dup-b", "operator", _anchor("stairs", 30.4, 20.3, 3)),
    )
    merge = {"anchor_ids": ["dup-a", "dup-b"]}
    at(
        0.45,
        Step("merge dup-a and dup-b", "POST", f"{anchors}:merge", "operator", merge, again=frozenset({409})),
    )
    at(0.55, Step("delete the kiosk", "DELETE", f"{anchors}/kiosk", "operator", again=frozenset({404})))
    at(0.60, Step("signal map", "POST", f"/v1/buildings/{BUILDING}/signal-maps", "operator", killable=False))
    at(0.50, Step("draw zone-late", "PUT", f"{zones}/zone-late", "operator", _zone(sim, 2, 0.8)))
    at(0.65, Step("delete zone-3", "DELETE", f"{zones}/zone-3", "operator", again=frozenset({404})))
    forget = f"/v1/buildings/{BUILDING}/users/{FORGOTTEN}"
    at(0.70, Step("forget phone 4", "DELETE", forget, "operator", again=frozenset({404})))
    revoke = f"/v1/buildings/{BUILDING}/keys/{{prefix of {FORGOTTEN}}}"
    at(0.72, Step("revoke", "DELETE", revoke, "operator", again=frozenset({404})))

    steps: list[Step] = []
    forgotten = False
    for i, b in enumerate(walked):
        for step in edits.get(i, []):
            steps.append(step)
            forgotten = forgotten or step.name == "forget phone 4"
        if forgotten and b.device_id == FORGOTTEN:
            continue  # its person has left
        steps.append(Step(b.batch_id, "POST", f"/v1/buildings/{BUILDING}/batches", b.device_id, batch=b))
    return CrashScenario(
        sim, setup, steps, devices, batches={s.batch.batch_id: s.batch for s in steps if s.batch is not None}
    )


def _rises(sim: Simulation, user: int) -> dict[str, float]:
    """The rise of each way between floors the user took (metres; its phone, without a barometer, reports it
    with its detection of the way), by the way's anchor type."""
    elevations = sim.scenario.raw["storeys"]["elevations_m"]
    return {way: float(elevations[to] - elevations[frm]) for _, frm, to, way in sim.users[user].transitions}


def _zone(sim: Simulation, user: int, share: float) -> dict[str, Any]:
    """A 10 m square zone, with a 20 s dwell, around where the user truly is ``share`` into its walk (on its
    floor there)."""
    tr = sim.users[user]
    k = int(share * (len(tr.t) - 1))
    x, y = (float(v) for v in tr.xy[k])
    width, height = (float(sim.scenario["floor"][n]) for n in ("width_m", "height_m"))
    x0, x1 = max(0.0, x - 5.0), min(width, x + 5.0)
    y0, y1 = max(0.0, y - 5.0), min(height, y + 5.0)
    ring = [[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]
    return {
        "floor": tr.level_at(float(tr.t[k])) + FLOOR_OFFSET,
        "name": f"around phone {user}",
        "polygon": {"type": "Polygon", "coordinates": [ring]},
        "dwell_s": 20.0,
    }


def _size(floor: dict[str, Any]) -> dict[str, float]:
    return {"width_m": float(floor["width_m"]), "height_m": float(floor["height_m"])}


def _true_fix(sim: Simulation, user: int, batch: SensorBatch) -> PositionFix:
    """Where the user truly is at the batch's first step, as a surveyor would tell it."""
    tr = sim.users[user]
    t_ms = batch.steps[0].t_ms
    k = int(np.argmin(np.abs(tr.t * 1000.0 + EPOCH_MS - t_ms)))
    return PositionFix(
        t_ms=t_ms,
        position=Position(x_m=float(tr.xy[k, 0]), y_m=float(tr.xy[k, 1])),
        sigma_m=0.5,
        floor=tr.level_at(float(tr.t[k])) + FLOOR_OFFSET,
    )
