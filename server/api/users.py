"""A building's users: an operator makes the server forget one (a person who asks to be forgotten, a
finished crowd)."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from schemas.common import Identifier
from server.api.contract import problems
from server.api.deps import Caller, State
from server.buildings.calls import ForgetUser

router = APIRouter(prefix="/v1/buildings/{building_id}", tags=["users"])


@router.delete(
    "/users/{user_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=problems(
        403, (404, "No such building, or no user of this id tracked or stored in it."), 422, 503
    ),
)
async def forget_user(building_id: str, user_id: Identifier, caller: Caller, state: State) -> Response:
    """Forget a user (operator key): its filter, its latest position and its whole position history.
    Dashboards are told to drop it. The recordings keep its batches until their retention ends
    (``docs/operations.md`` says how to remove them sooner). A later batch of its device starts a new
    filter: revoke the device's key to stop it posting."""
    caller.require_operator(building_id)
    building = await state.tracking.handle(building_id)
    messages = await building.ask(ForgetUser(user_id))
    building.publish(messages)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
