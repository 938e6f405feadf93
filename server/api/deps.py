"""FastAPI dependencies: the app state, a database session, the caller's key."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request, Security
from sqlalchemy.orm import Session

from server.api.contract import BearerKey
from server.auth import Principal, authenticate, bearer_secret
from server.state import AppState
from server.store import repositories as repo


def get_state(request: Request) -> AppState:
    state: AppState = request.app.state.crowdslam
    return state


State = Annotated[AppState, Depends(get_state)]


def get_session(state: State) -> Iterator[Session]:
    with state.sessions() as session:
        yield session


DbSession = Annotated[Session, Depends(get_session)]


async def principal(state: AppState, authorization: str | None) -> Principal:
    """The caller behind an Authorization header: from the key cache, else from the database."""
    secret = bearer_secret(authorization)
    now = time.monotonic()
    if secret is not None and (cached := state.keys.get(secret, now)) is not None:
        return cached

    def lookup() -> Principal:
        with state.sessions() as session:
            return authenticate(session, secret)

    found = await asyncio.to_thread(lookup)
    state.keys.used(found.key_id)
    if secret is not None:
        state.keys.put(secret, found, now)
    return found


async def revalidate_keys(state: AppState) -> None:
    """One round of the key cache's revalidation (``KeyCache.revalidate``): one query for every cached key."""
    ids = state.keys.key_ids()
    if not ids:
        return
    checked_at = time.monotonic()
    used = state.keys.take_used()

    def query() -> set[int]:
        with state.sessions.begin() as session:
            repo.touch_keys(session, used)  # when each was last used, for the operators' key lists
            return repo.valid_key_ids(session, ids)

    state.keys.revalidate(await asyncio.to_thread(query), checked_at)


async def token_principal(state: AppState, token: str | None) -> Principal:
    """The caller behind a WebSocket's ``?token=<key>``, through the same key cache (and off the loop)."""
    return await principal(state, None if not token else f"Bearer {token}")


async def get_principal(
    state: State, authorization: Annotated[str | None, Security(BearerKey())] = None
) -> Principal:
    return await principal(state, authorization)


Caller = Annotated[Principal, Depends(get_principal)]
