"""FastAPI dependencies: the app state, a database session, the caller's key."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Header, Request
from sqlalchemy.orm import Session

from server.app import AppState
from server.auth import Principal, authenticate, bearer_secret


def get_state(request: Request) -> AppState:
    state: AppState = request.app.state.crowdslam
    return state


State = Annotated[AppState, Depends(get_state)]


def get_session(state: State) -> Iterator[Session]:
    with state.sessions() as session:
        yield session


DbSession = Annotated[Session, Depends(get_session)]


async def get_principal(
    state: State, authorization: Annotated[str | None, Header(description="Bearer <API key>")] = None
) -> Principal:
    secret = bearer_secret(authorization)
    now = time.monotonic()
    if secret is not None and (cached := state.keys.get(secret, now)) is not None:
        return cached

    def lookup() -> Principal:
        with state.sessions() as session:
            return authenticate(session, secret)

    principal = await asyncio.to_thread(lookup)
    if secret is not None:
        state.keys.put(secret, principal, now)
    return principal


Caller = Annotated[Principal, Depends(get_principal)]
