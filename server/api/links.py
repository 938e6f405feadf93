"""OpenAPI links: which later operation a response's values lead to (a building created, then its keys and
anchors; a key minted, then its revocation; an anchor pinned, then read or deleted; a build started, then
its status). Client generators and stateful API testers follow them."""

from __future__ import annotations

from typing import Any


def link(method: str, path: str, description: str, **parameters: str) -> dict[str, Any]:
    """A link to the operation ``method path``, its parameters given as runtime expressions
    (``$response.body#/id``, ``$request.path.building_id``)."""
    pointer = path.replace("~", "~0").replace("/", "~1")
    return {
        "operationRef": f"#/paths/{pointer}/{method.lower()}",
        "parameters": parameters,
        "description": description,
    }


def links(status: int, **named: dict[str, Any]) -> dict[int | str, dict[str, Any]]:
    """A route's ``responses`` entry declaring the links of its ``status`` response."""
    return {status: {"links": named}}


BUILDING = "/v1/buildings/{building_id}"
SAME_BUILDING = "$request.path.building_id"
