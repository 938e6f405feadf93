"""The key presented: what it may do, so a client shows only the actions it will be allowed."""

from __future__ import annotations

from fastapi import APIRouter

from schemas.api import KeyIdentity
from server.api.deps import Caller

router = APIRouter(prefix="/v1", tags=["keys"])


@router.get("/key", response_model=KeyIdentity)
async def get_current_key(caller: Caller) -> KeyIdentity:
    """The presented key's scope and building (any valid key; 401 otherwise)."""
    return KeyIdentity(scope=caller.scope, building_id=caller.building_id, device_id=caller.device_id)
