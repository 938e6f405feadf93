"""Sending the queued webhook deliveries.

A delivery is queued in the transaction of the batch whose event it carries (``repositories.
enqueue_deliveries``), so a batch never waits for a receiver, and an event committed is delivered even if
the server crashes before sending it. The dispatcher, a task of each serving process, claims for each
webhook its oldest pending delivery once due (a webhook's deliveries go one at a time, so a user's events
arrive in order), POSTs it signed, and records the answer: 2xx is delivered; anything else (an error
status, a redirect, which is never followed, a timeout, a refused connection) is tried again after
``webhook_retry_s``, doubled each time, until ``webhook_max_attempts``. Then the delivery gives up and the
webhook is suspended (its pending deliveries given up, no new ones) until an operator PUTs it again: a dead
receiver costs one row per event for minutes, not a queue without end.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import logging
import time
from dataclasses import dataclass
from urllib.parse import urlsplit, urlunsplit

import httpx
from sqlalchemy.orm import Session, sessionmaker

from server.store import repositories as repo
from server.store.models import WebhookDeliveryRow
from server.webhooks.addresses import AllowedHosts, RefusedAddressError, resolve

logger = logging.getLogger(__name__)

SIGNATURE_HEADER = "X-Crowdslam-Signature"
MAX_BACKOFF_S = 600.0
HOLD_S = 60.0
"""How long a claim holds a delivery: a dispatcher that died sending it leaves it to another after this."""
CONCURRENT = 8
"""Deliveries in flight at once (each to another webhook)."""
LOG_DAYS = 7.0
"""Finished deliveries are kept this long in the delivery log."""


def signature(secret: str, body: bytes) -> str:
    """``sha256=<hex HMAC-SHA256 of the body with the secret>``: what a receiver recomputes to trust a
    delivery."""
    return "sha256=" + hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()


@dataclass(frozen=True)
class DispatchConfig:
    allowed: AllowedHosts
    max_attempts: int
    retry_s: float
    timeout_s: float
    poll_s: float = 0.25


class Dispatcher:
    def __init__(self, sessions: sessionmaker[Session], config: DispatchConfig) -> None:
        self._sessions = sessions
        self._config = config
        self._wake = asyncio.Event()
        self._client = httpx.AsyncClient(follow_redirects=False, timeout=config.timeout_s, trust_env=False)
        self._pruned = 0.0

    def nudge(self) -> None:
        """Events were queued: look now rather than at the next poll."""
        self._wake.set()

    async def run(self) -> None:
        """Until cancelled: claim what is due, send it, wait for the next poll or a nudge."""
        try:
            while True:
                try:
                    await self.once()
                except Exception:  # the store is down, say: logged, and tried again at the next poll
                    logger.exception("webhook dispatch failed")
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), self._config.poll_s)
                self._wake.clear()
        finally:
            await self._client.aclose()

    async def once(self) -> int:
        """One round: every due head delivery sent (``CONCURRENT`` at a time); how many were sent."""
        now_ms = int(time.time() * 1000)
        claimed = await asyncio.to_thread(self._claim, now_ms)
        if claimed:
            gate = asyncio.Semaphore(CONCURRENT)

            async def send(row: WebhookDeliveryRow) -> None:
                async with gate:
                    await self._send(row)

            await asyncio.gather(*(send(row) for row in claimed))
        if time.monotonic() - self._pruned > 3600.0:
            self._pruned = time.monotonic()
            await asyncio.to_thread(self._prune, now_ms)
        return len(claimed)

    def _claim(self, now_ms: int) -> list[WebhookDeliveryRow]:
        with self._sessions.begin() as session:
            rows = repo.claim_due_deliveries(session, now_ms, int(HOLD_S * 1000), 64)
            session.expunge_all()
            return rows

    def _prune(self, now_ms: int) -> None:
        with self._sessions.begin() as session:
            repo.prune_deliveries(session, now_ms - int(LOG_DAYS * 86_400_000), 10_000)

    async def _send(self, row: WebhookDeliveryRow) -> None:
        hook = await asyncio.to_thread(self._webhook, row.building_id, row.webhook_id)
        if hook is None:
            return  # deleted meanwhile, with its deliveries
        url, secret = hook
        body = row.body.encode()
        status: int | None = None
        error: str | None = None
        refused = False
        try:
            target, headers, extensions = await asyncio.to_thread(self._target, url)
            headers |= {"Content-Type": "application/json", SIGNATURE_HEADER: signature(secret, body)}
            response = await self._client.post(target, content=body, headers=headers, extensions=extensions)
            status = response.status_code
            if not 200 <= status < 300:
                error = f"the receiver answered {status}" + (
                    " (a redirect, which is not followed)" if 300 <= status < 400 else ""
                )
        except RefusedAddressError as exc:  # the same at every try: given up at once
            error, refused = str(exc), True
        except httpx.HTTPError as exc:
            error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        await asyncio.to_thread(self._record, row, status, error, refused)

    def _webhook(self, building_id: str, webhook_id: str) -> tuple[str, str] | None:
        with self._sessions() as session:
            hook = repo.get_webhook(session, building_id, webhook_id)
            return None if hook is None else (hook.url, hook.secret)

    def _target(self, url: str) -> tuple[str, dict[str, str], dict[str, str]]:
        """The URL with its host replaced by the address checked now (so that the connection goes where the
        check looked), the Host header and the TLS server name of the original."""
        parts = urlsplit(url)
        host = parts.hostname or ""
        port = parts.port or (443 if parts.scheme == "https" else 80)
        address = resolve(host, port, self._config.allowed)
        netloc = f"[{address}]" if address.version == 6 else str(address)
        target = urlunsplit((parts.scheme, f"{netloc}:{port}", parts.path or "/", parts.query, ""))
        host_header = host if parts.port is None else f"{host}:{parts.port}"
        return target, {"Host": host_header}, {"sni_hostname": host}

    def _record(self, row: WebhookDeliveryRow, status: int | None, error: str | None, refused: bool) -> None:
        now_ms = int(time.time() * 1000)
        attempts = row.attempts + 1
        with self._sessions.begin() as session:
            if error is None:
                repo.finish_attempt(
                    session,
                    row.id,
                    status="delivered",
                    http_status=status,
                    error=None,
                    delivered_ms=now_ms,
                    next_attempt_ms=None,
                )
                return
            if attempts >= self._config.max_attempts or refused:
                repo.finish_attempt(
                    session, row.id, status="gave_up", http_status=status, error=error, next_attempt_ms=None
                )
                repo.suspend_webhook(
                    session,
                    row.building_id,
                    row.webhook_id,
                    f"not sent: delivery {row.id} gave up after {attempts} tries; the webhook is suspended",
                )
                logger.warning(
                    "webhook %s of building %s suspended: %s", row.webhook_id, row.building_id, error
                )
                return
            backoff = min(MAX_BACKOFF_S, self._config.retry_s * 2 ** (attempts - 1))
            repo.finish_attempt(
                session,
                row.id,
                http_status=status,
                error=error,
                next_attempt_ms=now_ms + int(backoff * 1000),
            )
