"""FastAPI dependencies: the app state, a database session, the caller's key."""

from __future__ import annotations

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


def get_principal(
    state: State, authorization: Annotated[str | None, Header(description="Bearer <API key>")] = None
) -> Principal:
    with state.sessions() as session:
        return authenticate(session, bearer_secret(authorization))


Caller = Annotated[Principal, Depends(get_principal)]
