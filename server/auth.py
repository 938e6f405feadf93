"""API keys: minting, hashing and scope rules. Keys read ``csk_<prefix>_<secret>``; only SHA-256 is kept."""

from __future__ import annotations

import secrets
import time
from collections.abc import Collection
from dataclasses import dataclass
from datetime import UTC, datetime

from sqlalchemy.orm import Session

from schemas.api import KeyScope
from server.errors import ForbiddenError, UnauthorizedError
from server.store import repositories as repo


@dataclass(frozen=True)
class Principal:
    key_id: int
    scope: KeyScope
    building_id: str | None  # None: a site-wide operator key
    device_id: str | None

    def require_operator(self, building_id: str | None = None) -> None:
        """Operators manage their building; a site-wide operator key (no building) manages every one."""
        if self.scope != KeyScope.OPERATOR:
            raise ForbiddenError(f"this needs an operator key; the key presented is a {self.scope.value} key")
        if building_id is not None and self.building_id not in (None, building_id):
            raise ForbiddenError(
                f"this operator key manages building {self.building_id!r}, not {building_id!r}"
            )

    def require_reader(self, building_id: str) -> None:
        """Dashboards read their building; operators read what they manage."""
        if self.scope == KeyScope.DEVICE:
            raise ForbiddenError(
                "device keys post batches; reading positions needs a dashboard or operator key"
            )
        if self.building_id not in (None, building_id):
            raise ForbiddenError(f"this key is for building {self.building_id!r}, not {building_id!r}")

    def require_member(self, building_id: str) -> None:
        """Any key of the building reads what every client of it needs: the building, its floors and their
        plans (a phone draws itself on them). A site-wide operator key reads every building."""
        if self.building_id not in (None, building_id):
            raise ForbiddenError(f"this key is for building {self.building_id!r}, not {building_id!r}")

    def require_own_device(self, building_id: str, device_id: str) -> None:
        """A device key reads its own device only; dashboards and operators read any of their building's."""
        if self.scope != KeyScope.DEVICE:
            self.require_reader(building_id)
            return
        self.require_member(building_id)
        if self.device_id != device_id:
            raise ForbiddenError(
                f"a device key reads its own device only; this key's device is {self.device_id!r}, "
                f"not {device_id!r}"
            )

    def require_device(self, building_id: str, device_id: str | None) -> None:
        """A device key posts only as its own device (None: not known yet) in its own building."""
        if self.scope != KeyScope.DEVICE:
            raise ForbiddenError(
                f"posting batches needs a device key; the key presented is a {self.scope.value} key"
            )
        if self.building_id != building_id:
            raise ForbiddenError(f"this device key is for building {self.building_id!r}, not {building_id!r}")
        if device_id is not None and self.device_id != device_id:
            raise ForbiddenError(f"this device key posts as device {self.device_id!r}, not {device_id!r}")


def key_prefix(secret: str) -> str | None:
    """The prefix a key is listed and revoked by (``csk_<prefix>_<secret>``); None for what is not a key."""
    parts = secret.split("_", 2)
    return parts[1] if len(parts) == 3 and parts[0] == "csk" and parts[1] else None


def mint_key(
    session: Session, scope: KeyScope, building_id: str | None = None, device_id: str | None = None
) -> tuple[str, str]:
    """Create a key; returns (secret, prefix). The caller commits."""
    prefix = secrets.token_hex(4)
    secret = f"csk_{prefix}_{secrets.token_urlsafe(24)}"
    repo.insert_key(session, prefix, secret, scope.value, building_id, device_id)
    return secret, prefix


def authenticate(session: Session, secret: str | None) -> Principal:
    if not secret:
        raise UnauthorizedError(
            "send an API key as 'Authorization: Bearer <key>' (or ?token=<key> on WebSockets)"
        )
    row = repo.find_key(session, secret)
    if row is None:
        raise UnauthorizedError("the API key is unknown or revoked")
    return Principal(row.id, KeyScope(row.scope), row.building_id, row.device_id)


def bearer_secret(authorization: str | None) -> str | None:
    if authorization is None:
        return None
    scheme, _, value = authorization.partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        raise UnauthorizedError("the Authorization header must read 'Bearer <key>'")
    return value.strip()


class KeyCache:
    """Recently authenticated keys, so a phone posting every second costs no database query. An entry
    lives ``ttl_s`` seconds: a key revoked in the database stops working within that time. The server
    revalidates every cached key in one query every ``ttl_s / 2`` (``revalidate``), which extends the
    entries of keys still valid: keys in use do not expire together (a thousand phones that started
    together would otherwise all query the database in the same second)."""

    def __init__(self, ttl_s: float, max_entries: int = 100_000) -> None:
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self._entries: dict[str, tuple[Principal, float]] = {}
        self._used: dict[int, int] = {}  # key id -> minute of its latest use (Unix minutes)

    def get(self, secret: str, now: float) -> Principal | None:
        entry = self._entries.get(secret)
        if entry is None or entry[1] < now:
            return None
        self.used(entry[0].key_id)
        return entry[0]

    def used(self, key_id: int) -> None:
        """A request was made with this key (its minute is written at the next revalidation)."""
        self._used[key_id] = int(time.time()) // 60

    def take_used(self) -> dict[int, datetime]:
        """The keys used since the last call, with the minute of their latest use."""
        used, self._used = self._used, {}
        return {key_id: datetime.fromtimestamp(minute * 60, UTC) for key_id, minute in used.items()}

    def forget(self, key_ids: Collection[int]) -> None:
        """Keys revoked by this process: refused from the next request on (other processes refuse them
        within ``ttl_s``)."""
        gone = set(key_ids)
        self._entries = {s: e for s, e in self._entries.items() if e[0].key_id not in gone}

    def put(self, secret: str, principal: Principal, now: float) -> None:
        if self.ttl_s <= 0:
            return
        if len(self._entries) >= self.max_entries:
            self._entries = {k: v for k, v in self._entries.items() if v[1] >= now}
            if len(self._entries) >= self.max_entries:
                self._entries.clear()
        self._entries[secret] = (principal, now + self.ttl_s)

    def key_ids(self) -> set[int]:
        """The database ids of the cached keys."""
        return {principal.key_id for principal, _ in self._entries.values()}

    def revalidate(self, valid_key_ids: set[int], checked_at: float) -> None:
        """Keys found valid by a query that started at ``checked_at`` live ``ttl_s`` from then; the
        others are forgotten (the next request with them is checked against the database)."""
        self._entries = {
            secret: (principal, max(until, checked_at + self.ttl_s))
            for secret, (principal, until) in self._entries.items()
            if principal.key_id in valid_key_ids
        }
