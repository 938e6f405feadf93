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


class HistorySampling:
    """Which estimates join their users' position history: one a ``period_s`` of the phone's time (a history
    dense enough for the dashboard's slider, not one row per batch). Its memory (each user's latest row of
    history) is part of the building's snapshot, and the batches a restart replays go through it again, so
    a crash leaves the history as it would have been."""

    def __init__(self, period_s: float, latest_t_ms: dict[str, int] | None = None) -> None:
        self.period_ms = period_s * 1000.0
        self.latest_t_ms: dict[str, int] = {} if latest_t_ms is None else latest_t_ms

    def joins(self, user_id: str, t_ms: int) -> bool:
        """Whether the user's estimate at ``t_ms`` joins its history (and, if so, it is the latest now)."""
        last = self.latest_t_ms.get(user_id)
        if last is not None and 0 <= t_ms - last < self.period_ms:
            return False
        self.latest_t_ms[user_id] = t_ms
        return True

    def forget(self, user_id: str) -> None:
        self.latest_t_ms.pop(user_id, None)
