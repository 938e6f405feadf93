"""Operators name where a building's zone events are POSTed (webhooks) and read each one's delivery log."""

from __future__ import annotations

import asyncio
from typing import Annotated
from urllib.parse import urlsplit

from fastapi import APIRouter, Query, Response, status

from schemas.common import Identifier
from schemas.zones import MAX_WEBHOOKS, Webhook, WebhookDelivery, WebhookIn
from server.api.contract import PROBLEMS, problems
from server.api.deps import Caller, State
from server.api.links import BUILDING, SAME_BUILDING, link, links
from server.errors import InvalidInputError, NotFoundError
from server.store import repositories as repo
from server.store.models import WebhookDeliveryRow, WebhookRow
from server.webhooks.addresses import AllowedHosts, RefusedAddressError, resolve

router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["webhooks"])

_HOOK = f"{BUILDING}/webhooks/{{webhook_id}}"
_THIS_HOOK = {"building_id": SAME_BUILDING, "webhook_id": "$response.body#/id"}
_NO_HOOK = (404, "No such building, or no webhook of this id in it.")


def _webhook(row: WebhookRow) -> Webhook:
    return Webhook(
        id=row.id,
        url=row.url,
        events=row.events.split(","),
        suspended=row.suspended_at is not None,
    )


def _delivery(row: WebhookDeliveryRow) -> WebhookDelivery:
    return WebhookDelivery.model_validate(
        {
            "id": row.id,
            "webhook_id": row.webhook_id,
            "event": row.event,
            "body": row.body,
            "created_ms": row.created_ms,
            "attempts": row.attempts,
            "status": row.status,
            "http_status": row.http_status,
            "error": row.error,
            "next_attempt_ms": row.next_attempt_ms,
            "delivered_ms": row.delivered_ms,
        }
    )


@router.put(
    "/webhooks/{webhook_id}",
    response_model=Webhook,
    responses={
        **problems(
            400,
            403,
            (404, "No such building."),
            413,
            (
                422,
                PROBLEMS[422] + " A host that resolves to a loopback, link-local or private address (unless "
                "the server's CROWDSLAM_WEBHOOK_ALLOWED_HOSTS lists it), or a building's webhook beyond the "
                "most it may hold, is refused.",
            ),
        ),
        **links(
            200,
            Deliveries=link("GET", f"{_HOOK}/deliveries", "Its delivery log.", **_THIS_HOOK),
            DeleteWebhook=link("DELETE", _HOOK, "Delete it.", **_THIS_HOOK),
        ),
    },
)
async def put_webhook(
    building_id: str, webhook_id: Identifier, body: WebhookIn, caller: Caller, state: State
) -> Webhook:
    """Name where the building's zone events are POSTed (operator key), and which: ``zone.enter``,
    ``zone.exit``, ``zone.dwell``. Each delivery's JSON body is signed in ``X-Crowdslam-Signature:
    sha256=<hex HMAC-SHA256 of the body with the secret>``; a webhook's deliveries arrive one at a time, in
    the order of its events; a failed one is tried again with backoff, and after the last try the webhook is
    suspended until it is PUT again (which this does). Redirects are not followed."""
    caller.require_operator(building_id)
    url = str(body.url)
    parts = urlsplit(url)
    allowed = AllowedHosts.parse(state.settings.webhook_allowed_hosts)
    try:
        await asyncio.to_thread(
            resolve, parts.hostname or "", parts.port or (443 if parts.scheme == "https" else 80), allowed
        )
    except RefusedAddressError as exc:
        raise InvalidInputError(f"the webhook's url cannot be used: {exc}") from None

    def store() -> Webhook:
        with state.sessions.begin() as session:
            if repo.get_building(session, building_id) is None:
                raise NotFoundError(f"no building {building_id!r}")
            others = [h for h in repo.list_webhooks(session, building_id) if h.id != webhook_id]
            if len(others) >= MAX_WEBHOOKS:
                raise InvalidInputError(
                    f"building {building_id!r} has {MAX_WEBHOOKS} webhooks, the most it may hold"
                )
            row = {
                "building_id": building_id,
                "id": webhook_id,
                "url": url,
                "secret": body.secret,
                "events": ",".join(body.events),
            }
            repo.save_webhook(session, row)
        return Webhook(id=webhook_id, url=url, events=body.events, suspended=False)

    return await asyncio.to_thread(store)


@router.get("/webhooks", response_model=list[Webhook], responses=problems(403, (404, "No such building.")))
async def list_webhooks(building_id: str, caller: Caller, state: State) -> list[Webhook]:
    """The building's webhooks, without their secrets (operator key)."""
    caller.require_operator(building_id)

    def query() -> list[Webhook]:
        with state.sessions() as session:
            if repo.get_building(session, building_id) is None:
                raise NotFoundError(f"no building {building_id!r}")
            return [_webhook(h) for h in repo.list_webhooks(session, building_id)]

    return await asyncio.to_thread(query)


@router.delete(
    "/webhooks/{webhook_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=problems(403, _NO_HOOK),
)
async def delete_webhook(building_id: str, webhook_id: Identifier, caller: Caller, state: State) -> Response:
    """Delete a webhook and its delivery log (operator key); deliveries pending are not sent."""
    caller.require_operator(building_id)

    def remove() -> bool:
        with state.sessions.begin() as session:
            return repo.delete_webhook(session, building_id, webhook_id)

    if not await asyncio.to_thread(remove):
        raise NotFoundError(f"no webhook {webhook_id!r} in building {building_id!r}")
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get(
    "/webhooks/{webhook_id}/deliveries",
    response_model=list[WebhookDelivery],
    responses=problems(403, _NO_HOOK, 422),
)
async def list_webhook_deliveries(
    building_id: str,
    webhook_id: Identifier,
    caller: Caller,
    state: State,
    limit: Annotated[int, Query(ge=1, le=1_000)] = 100,
) -> list[WebhookDelivery]:
    """The webhook's latest deliveries, newest first (operator key): each event's body as sent, its tries,
    the receiver's last answer or error, and when it was delivered or will be tried again."""
    caller.require_operator(building_id)

    def query() -> list[WebhookDelivery]:
        with state.sessions() as session:
            if repo.get_webhook(session, building_id, webhook_id) is None:
                raise NotFoundError(f"no webhook {webhook_id!r} in building {building_id!r}")
            return [_delivery(d) for d in repo.webhook_deliveries(session, building_id, webhook_id, limit)]

    return await asyncio.to_thread(query)
