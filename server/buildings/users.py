"""A building's users as people and operators change them: a device assigned to a user, a user forgotten on
request, users forgotten when idle (``Retention.user_idle_s``), and when each was last heard."""

from __future__ import annotations

import time
from collections.abc import Callable

from schemas.live import LiveMessage, UserForgottenMessage
from server.buildings.building import Building, SaveSnapshot
from server.errors import NotFoundError
from server.store import repositories as repo


class Users:
    def __init__(self, building: Building, save_snapshot: SaveSnapshot, reload: Callable[[], None]) -> None:
        self.building = building
        self._save_snapshot = save_snapshot
        self._reload = reload
        self._last_heard: dict[str, float] = {}  # user -> wall time of its last applied batch

    def heard(self, users: list[str]) -> None:
        """These users' batches were applied now."""
        now = time.time()
        for user in users:
            self._last_heard[user] = now

    def forget(self, user_id: str) -> list[LiveMessage]:
        """Forget a user, as a person may ask: its filter, its latest position, its history and its zone
        visits. A snapshot is written in the same transaction, so a restart does not bring the user back from
        the batch log; a later batch of its device starts a new filter. The recordings keep its batches (see
        the operations document). State changes only if the transaction commits."""
        b = self.building
        tracked = user_id in b.tracker.users
        if tracked:
            b.tracker.remove_user(user_id)
            b.device_of_user.pop(user_id, None)
            self._last_heard.pop(user_id, None)
            b.history.forget(user_id)
        try:
            with b.writer_turns, b.sessions.begin() as session:
                deleted = repo.delete_user_positions(session, b.building_id, user_id)
                deleted += repo.delete_user_visits(session, b.building_id, user_id)
                if not tracked and not deleted:
                    raise NotFoundError(f"no user {user_id!r} in building {b.building_id!r}")
                rows = self._save_snapshot(session) if tracked else []
        except NotFoundError:
            raise
        except Exception:
            if tracked:
                self._reload()  # the user's filter back, as the database still has it
            raise
        b.devices.saved(rows)
        return [UserForgottenMessage(user_id=user_id)]

    def assign_device(self, device_id: str, user_id: str) -> None:
        """An operator assigns a device to a user: its batches are for that user from now on."""
        b = self.building
        row = b.devices.assign(device_id, user_id)
        with b.writer_turns, b.sessions.begin() as session:
            repo.upsert_devices(session, [row])
        b.devices.saved([row])

    def evict_idle(self) -> list[str]:
        """Forget the users not heard from for ``Retention.user_idle_s``: called right before a snapshot is
        written, so a restart's replay never spans an eviction. Returns them (their visits are closed in the
        snapshot's transaction)."""
        b = self.building
        idle_s = b.config.retention.user_idle_s
        if idle_s is None:
            return []
        now = time.time()
        idle = [u for u in b.tracker.users if now - self._last_heard.setdefault(u, now) > idle_s]
        if idle:
            b.tracker.remove_users(idle)
            for u in idle:
                del self._last_heard[u]
                b.history.forget(u)
            b.counters.users_evicted += len(idle)
        return idle
