"""What the app holds while it runs (``app.state.crowdslam``): built by the lifespan, read by the routers."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from server.auth import KeyCache
from server.buildings.registry import Buildings
from server.live.broadcast import Broadcaster
from server.metrics import Metrics
from server.rate_limit import RateLimiter
from server.settings import Settings
from server.signal_maps.jobs import SignalMapService
from server.storage import StorageWatch

if TYPE_CHECKING:
    from server.live.foxglove import FoxgloveLive  # the SDK is imported only when its port is set


@dataclass
class AppState:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    broadcaster: Broadcaster
    tracking: Buildings
    metrics: Metrics
    started: float
    keys: KeyCache
    signal_maps: SignalMapService
    storage: StorageWatch
    foxglove: FoxgloveLive | None = None
    rate: RateLimiter = field(default_factory=lambda: RateLimiter(0.0, 1.0))
    live_sockets: dict[int, int] = field(default_factory=dict)
    """Open live WebSockets per key id (``Settings.max_live_sockets_per_key``)."""
