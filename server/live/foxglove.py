"""Foxglove's live WebSocket server beside uvicorn (a second port): every building's live messages on
Foxglove's well-known schemas, so the Foxglove app or its open-source fork Lichtblick can watch a building
without a dashboard of our own (``ws://HOST:PORT`` in "Open connection").

Per building ``B`` (its frame is ``B``, metres in the building's local frame):
- ``/buildings/B/users`` (``foxglove.SceneUpdate``): a sphere per user at its estimate, as wide as two sigma
  of its larger axis, with the user id as a text label;
- ``/buildings/B/poses`` (``foxglove.PosesInFrame``): the latest pose of every user seen;
- ``/buildings/B/anchors`` (``foxglove.SceneUpdate``): a cube per crowd anchor (known anchors green), removed
  when an operator deletes it;
- ``/buildings/B/encounters`` (``foxglove.SceneUpdate``): a line between the two users of each encounter,
  where they met, shown for a few seconds.

The server has no authentication: it listens on loopback unless told otherwise (``CROWDSLAM_FOXGLOVE_HOST``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import foxglove
from foxglove.channels import PosesInFrameChannel, SceneUpdateChannel
from foxglove.messages import (
    Color,
    CubePrimitive,
    Duration,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    PosesInFrame,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from schemas.estimates import EncounterEvent, Estimate
from schemas.live import AnchorMessage, EncounterMessage, LiveMessage, PositionMessage
from slam_core.filter.kernels.linalg2 import largest_eigenvalue2

ENCOUNTER_SHOWN_S = 5
USER_COLOUR = Color(r=0.2, g=0.5, b=1.0, a=0.8)
ANCHOR_COLOUR = Color(r=1.0, g=0.6, b=0.1, a=0.9)
KNOWN_COLOUR = Color(r=0.1, g=0.8, b=0.3, a=0.9)
ENCOUNTER_COLOUR = Color(r=0.9, g=0.2, b=0.6, a=0.9)


def _stamp(t_ms: int) -> Timestamp:
    return Timestamp(sec=t_ms // 1000, nsec=(t_ms % 1000) * 1_000_000)


def _yaw(heading_rad: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(heading_rad / 2), w=math.cos(heading_rad / 2))


def _larger_sigma(cov: tuple[float, float, float]) -> float:
    return math.sqrt(max(largest_eigenvalue2(*cov), 0.0))


@dataclass
class _Building:
    users: SceneUpdateChannel
    poses: PosesInFrameChannel
    anchors: SceneUpdateChannel
    encounters: SceneUpdateChannel
    latest: dict[str, Estimate] = field(default_factory=dict)


class FoxgloveLive:
    """Call ``publish`` from the event loop (the SDK's channels are thread-safe and do not block)."""

    def __init__(self, host: str, port: int) -> None:
        self._context = foxglove.Context()
        self._server = foxglove.start_server(name="crowdslam", host=host, port=port, context=self._context)
        self._buildings: dict[str, _Building] = {}
        self.logged = 0

    @property
    def port(self) -> int:
        return int(self._server.port)

    @property
    def context(self) -> foxglove.Context:
        """The SDK context the channels log to (an MCAP writer opened on it records them too)."""
        return self._context

    def _building(self, building_id: str) -> _Building:
        b = self._buildings.get(building_id)
        if b is None:
            root = f"/buildings/{building_id}"
            b = self._buildings[building_id] = _Building(
                SceneUpdateChannel(f"{root}/users", context=self._context),
                PosesInFrameChannel(f"{root}/poses", context=self._context),
                SceneUpdateChannel(f"{root}/anchors", context=self._context),
                SceneUpdateChannel(f"{root}/encounters", context=self._context),
            )
        return b

    def publish(self, building_id: str, messages: list[LiveMessage]) -> None:
        b = self._building(building_id)
        estimates = [m.estimate for m in messages if isinstance(m, PositionMessage)]
        anchors = [m for m in messages if isinstance(m, AnchorMessage)]
        encounters = [m.encounter for m in messages if isinstance(m, EncounterMessage)]
        if estimates:
            for e in estimates:
                b.latest[e.user_id] = e
            t_ms = max(e.t_ms for e in estimates)
            b.users.log(SceneUpdate(entities=[_user_entity(building_id, e) for e in estimates]))
            b.poses.log(
                PosesInFrame(
                    timestamp=_stamp(t_ms),
                    frame_id=building_id,
                    poses=[_pose(e) for e in b.latest.values()],
                )
            )
        if anchors:
            b.anchors.log(
                SceneUpdate(
                    entities=[_anchor_entity(building_id, m) for m in anchors if not m.deleted],
                    deletions=[
                        SceneEntityDeletion(
                            timestamp=_stamp(m.anchor.last_seen_ms or 0),
                            type=SceneEntityDeletionType.MatchingId,
                            id=f"anchor/{m.anchor.id}",
                        )
                        for m in anchors
                        if m.deleted
                    ],
                )
            )
        lines = [_encounter_entity(building_id, e, b.latest) for e in encounters]
        if any(line is not None for line in lines):
            b.encounters.log(SceneUpdate(entities=[line for line in lines if line is not None]))
        self.logged += len(messages)

    def close(self) -> None:
        self._server.stop()


def _pose(e: Estimate) -> Pose:
    return Pose(position=Vector3(x=e.position.x_m, y=e.position.y_m, z=0.0), orientation=_yaw(e.heading_rad))


def _user_entity(building_id: str, e: Estimate) -> SceneEntity:
    c = e.covariance_m2
    width = max(2.0 * _larger_sigma((c[0][0], c[0][1], c[1][1])), 0.3)
    at = _pose(e)
    return SceneEntity(
        timestamp=_stamp(e.t_ms),
        frame_id=building_id,
        id=f"user/{e.user_id}",
        spheres=[SpherePrimitive(pose=at, size=Vector3(x=width, y=width, z=0.2), color=USER_COLOUR)],
        texts=[
            TextPrimitive(
                pose=at, billboard=True, font_size=14.0, scale_invariant=True, text=e.user_id,
                color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
            )
        ],
    )  # fmt: skip


def _anchor_entity(building_id: str, m: AnchorMessage) -> SceneEntity:
    a = m.anchor
    size = Vector3(x=0.8, y=0.8, z=0.8)
    centre = Pose(position=Vector3(x=a.position.x_m, y=a.position.y_m, z=0.4), orientation=_yaw(0.0))
    return SceneEntity(
        timestamp=_stamp(a.last_seen_ms or 0),
        frame_id=building_id,
        id=f"anchor/{a.id}",
        cubes=[CubePrimitive(pose=centre, size=size, color=KNOWN_COLOUR if a.known else ANCHOR_COLOUR)],
        texts=[
            TextPrimitive(
                pose=centre, billboard=True, font_size=12.0, scale_invariant=True,
                text=f"{a.type.value} ({a.observation_count})", color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
            )
        ],
    )  # fmt: skip


def _encounter_entity(building_id: str, e: EncounterEvent, latest: dict[str, Estimate]) -> SceneEntity | None:
    if e.position_a is not None and e.position_b is not None:  # where they met
        places = [e.position_a, e.position_b]
    else:
        a, b = latest.get(e.user_a), latest.get(e.user_b)
        if a is None or b is None:
            return None
        places = [a.position, b.position]
    points = [Point3(x=p.x_m, y=p.y_m, z=0.1) for p in places]
    return SceneEntity(
        timestamp=_stamp(e.t_ms),
        frame_id=building_id,
        id=f"encounter/{e.user_a}/{e.user_b}",
        lifetime=Duration(sec=ENCOUNTER_SHOWN_S, nsec=0),
        lines=[
            LinePrimitive(
                type=LinePrimitiveLineType.LineStrip, points=points, thickness=0.15, color=ENCOUNTER_COLOUR
            )
        ],
    )
