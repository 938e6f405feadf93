"""The SQL rows a building's tracking writes for its anchors and its users' estimates (wire models in, rows
out)."""

from __future__ import annotations

from schemas.anchors import BuildingAnchor
from schemas.estimates import Estimate
from server.store.models import AnchorRow


def anchor_row(building_id: str, a: BuildingAnchor) -> AnchorRow:
    return AnchorRow(
        building_id=building_id,
        public_id=a.id,
        floor=a.floor,
        type=a.type.value,
        x_m=a.position.x_m,
        y_m=a.position.y_m,
        cov_xx=a.covariance_m2[0][0],
        cov_xy=a.covariance_m2[0][1],
        cov_yy=a.covariance_m2[1][1],
        observation_count=a.observation_count,
        known=a.known,
        label=a.label,
        last_seen_ms=a.last_seen_ms,
        signature=a.signature.encode() if a.signature else None,
    )


def position_row(building_id: str, e: Estimate, stored_at_ms: int) -> dict[str, object]:
    return {
        "stored_at_ms": stored_at_ms,
        "building_id": building_id,
        "user_id": e.user_id,
        "device_id": e.device_id,
        "t_ms": e.t_ms,
        "x_m": e.position.x_m,
        "y_m": e.position.y_m,
        "cov_xx": e.covariance_m2[0][0],
        "cov_xy": e.covariance_m2[0][1],
        "cov_yy": e.covariance_m2[1][1],
        "heading_rad": e.heading_rad,
        "floor": e.floor,
        "floor_probability": e.floor_probability,
        "source": e.source.value,
    }
