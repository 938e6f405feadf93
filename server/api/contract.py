"""The OpenAPI contract as the server answers it: which problems each operation can answer, all as
``application/problem+json`` with the ``Problem`` schema; operation ids that read as method names in a
generated client; the bearer key as a security scheme; the raw ``SensorBatch`` body of the batch route.

Routes declare their problems with ``problems(...)``; ``install_openapi`` then writes every error response
of the spec the one way the server sends it, so a generated client in a typed language parses what it gets.
"""

from __future__ import annotations

import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.openapi.utils import get_openapi
from fastapi.routing import APIRoute
from fastapi.security import HTTPBearer

from schemas.errors import Problem
from schemas.sensors import SensorBatch
from server.errors import PROBLEM_MEDIA_TYPE

SECURITY_SCHEME = "bearerKey"
"""The security scheme's name in the spec: an API key sent as ``Authorization: Bearer <key>``."""

PROBLEMS: dict[int, str] = {
    400: "The body is not JSON, or a header is malformed.",
    401: "The key is missing, unknown or revoked (`WWW-Authenticate: Bearer`).",
    403: "The key's scope, building or device does not allow this.",
    404: "No such building, or no such item in it.",
    409: "The request conflicts with the building's current state.",
    413: "The body is larger than the server accepts.",
    422: "The input breaks the schema or one of the rules its description gives; `errors` lists the fields.",
    429: "Too many requests: send again after `Retry-After` seconds.",
    500: "The server could not apply the batch; nothing of it was kept, and the error was logged.",
    503: "The building is restarting or moving to another worker: send again (after `Retry-After` "
    "seconds when given).",
}
"""What each status means wherever it is answered; a route may say more for its own."""

_RETRY_AFTER = {
    "description": "Seconds to wait before sending again.",
    "schema": {"type": "integer", "minimum": 1},
}
_HEADERS: dict[int, dict[str, Any]] = {
    401: {
        "WWW-Authenticate": {
            "description": "The scheme to authenticate with.",
            "required": True,
            "schema": {"type": "string", "const": "Bearer"},
        }
    },
    429: {"Retry-After": {**_RETRY_AFTER, "required": True}},
    503: {"Retry-After": _RETRY_AFTER},
}


def problems(*statuses: int | tuple[int, str]) -> dict[int | str, dict[str, Any]]:
    """A route's ``responses`` entries for the problems it can answer: a status, or (status, what it means
    for this route)."""
    out: dict[int | str, dict[str, Any]] = {}
    for entry in statuses:
        status, description = entry if isinstance(entry, tuple) else (entry, PROBLEMS[entry])
        out[status] = {"model": Problem, "description": description}
    return out


class BearerKey(HTTPBearer):
    """The key as a security scheme, handing the raw header to ``server.auth`` (which tells a malformed
    header from a missing one, where ``HTTPBearer`` would see neither)."""

    def __init__(self) -> None:
        super().__init__(
            scheme_name=SECURITY_SCHEME,
            description="An API key: `Authorization: Bearer csk_...`. Operator keys come from "
            "`crowdslam keys create`; operators mint device and dashboard keys.",
            auto_error=False,
        )

    async def __call__(self, request: Request) -> str | None:  # type: ignore[override]
        return request.headers.get("authorization")


def operation_id(route: APIRoute) -> str:
    """The route's function name (``post_batch``, ``create_building``): generated clients name their
    methods after it. Stable as long as the function keeps its name; a test holds them unique."""
    return route.name


def allowed_methods(app: FastAPI, path: str) -> set[str]:
    """The methods the spec gives for this request path, from the path templates that match it with the
    fewest parameters: a 405's ``Allow``. (Starlette's own names only the first route whose path matched,
    while one path may be served by several routes.) Empty for a path the spec does not document."""
    matching = [
        (template.count("{"), item)
        for template, item in app.openapi()["paths"].items()
        if re.fullmatch(re.sub(r"\\{[^/}]+\\}", "[^/]+", re.escape(template)), path)
    ]
    # the templates with the fewest parameters: a literal segment names its own resource (``.../zones/
    # occupancy`` is not a zone's, whose id may not be ``occupancy``)
    fewest = min((n for n, _ in matching), default=0)
    methods = {method.upper() for n, item in matching if n == fewest for method in item}
    if "GET" in methods:
        methods.add("HEAD")
    return methods


def install_openapi(app: FastAPI) -> None:
    """Serve the spec as the server answers: the batch route's raw body documented as ``SensorBatch``; every
    secured operation answering 401; every error as ``application/problem+json``."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            spec = get_openapi(
                title=app.title,
                version=app.version,
                description=app.description,
                routes=app.routes,
                tags=app.openapi_tags,
            )
            components = spec.setdefault("components", {})
            schemas = components.setdefault("schemas", {})
            batch = SensorBatch.model_json_schema(ref_template="#/components/schemas/{model}")
            schemas.update(batch.pop("$defs", {}))
            schemas["SensorBatch"] = batch
            components.setdefault("securitySchemes", {})[SECURITY_SCHEME] = BearerKey().model.model_dump(
                mode="json", by_alias=True, exclude_none=True
            )
            for item in spec["paths"].values():
                for operation in item.values():
                    _write_problems(operation)
            for unused in ("HTTPValidationError", "ValidationError"):
                schemas.pop(unused, None)
            app.openapi_schema = spec
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


_PROBLEM_CONTENT = {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}}


def _write_problems(operation: dict[str, Any]) -> None:
    responses: dict[str, Any] = operation.setdefault("responses", {})
    if operation.get("security"):
        responses.setdefault("401", {"description": PROBLEMS[401]})
    for status, response in responses.items():
        if not status.isdigit() or int(status) < 400:
            continue
        if int(status) == 422 and response.get("description") == "Validation Error":  # FastAPI's default
            response["description"] = PROBLEMS[422]
        response["content"] = _PROBLEM_CONTENT
        if (headers := _HEADERS.get(int(status))) is not None:
            response["headers"] = headers
