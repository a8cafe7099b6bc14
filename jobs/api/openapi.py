"""The OpenAPI document as dncq really answers: the contract's error body wherever it comes.

FastAPI describes what the routes return on success and a 422 that dncq never sends. What
a client gets instead: the contract's `{"errorCode","errorMsg"[,"statusMsg"]}` with HTTP 200
from every `/api/cnc/` operation (beside its success shape, or instead of its file), 400 for
a request that cannot be parsed, 401/403/429 for the key, 413 for a body over the limit, and
404/409 from dncq's own resources. This module rewrites the generated document once so that
generated clients and schema-driven fuzzers expect exactly that.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from fastapi.routing import iter_route_contexts
from starlette.routing import BaseRoute

from jobs.api.deps import role_checks

ERROR_REF = {"$ref": "#/components/schemas/ContractError"}
ERROR_SCHEMA: dict[str, Any] = {
    "title": "ContractError",
    "type": "object",
    "description": "The gateway contract's error body (section 2.6); codes in docs/errors.md.",
    "properties": {
        "errorCode": {"type": "integer", "description": "0 is success"},
        "errorMsg": {"type": "string"},
        "statusMsg": {"type": "string", "description": "What exactly went wrong"},
    },
    "required": ["errorCode", "errorMsg"],
}
_ERRORS_BY_STATUS = {
    "400": "The request cannot be parsed: a parameter missing or malformed (20001)",
    "401": "No API key (X-Api-Key header, bearer token or apikey parameter), or a revoked one",
    "403": "A wrong API key (20403), or a role or machine list that does not allow this (20406)",
    "429": "Any API key from an address that sent too many wrong ones, until Retry-After "
           "seconds have passed (20429)",
}
_BODY_TOO_LARGE = "The request body is over the configured limit (20013)"
_RESOURCE_ERRORS = {"404": "No such resource", "409": "The resource cannot take this request"}
# dncq's own resources answer 422 where the body parses but what it asks for cannot be
# taken as it is (a machine whose options its transport refuses, targets given twice).
_UNPROCESSABLE = "The request parses but cannot be taken as it is; statusMsg says why"
_RESOURCE_PREFIXES = ("/api/jobs/", "/api/backups/", "/api/machines/", "/api/schedules/",
                      "/api/programs", "/api/runs", "/api/library", "/api/inbox",
                      "/api/gcodefiles", "/api/files", "/machines/", "/api/users",
                      "/api/keys", "/api/audit", "/api/lockouts/")
_TOO_LARGE = "Content too large for this operation (20012: a diff, a send job)"


def install(app: FastAPI) -> None:
    """Make `app.openapi()` (and so /openapi.json and /docs) describe dncq's real answers."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            document = get_openapi(title=app.title, version=app.version,
                                   description=app.description, routes=app.routes)
            app.openapi_schema = with_roles(truthful(document), app.routes)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def truthful(document: dict[str, Any]) -> dict[str, Any]:
    """The generated document with every operation's error answers as dncq sends them."""
    schemas = document.setdefault("components", {}).setdefault("schemas", {})
    schemas["ContractError"] = ERROR_SCHEMA
    for path, operations in document.get("paths", {}).items():
        for operation in operations.values():
            _rewrite(path, operation)
    for unused in ("HTTPValidationError", "ValidationError"):
        schemas.pop(unused, None)
    return document


def with_roles(document: dict[str, Any], routes: list[BaseRoute]) -> dict[str, Any]:
    """Each operation says the role it needs (`x-dncq-role`) and whether the machine it
    names must be one of an operator's (`x-dncq-machine-scoped`), in its text too."""
    for route in iter_route_contexts(routes):  # included routers' routes as they are served
        checks = role_checks(route)
        if not checks:
            continue
        needed = max((c.role for c in checks), key=lambda r: r.rank)
        scoped = any(c.scoped for c in checks)
        for method in route.methods or ():
            operation = document["paths"].get(route.path_format or "", {}).get(method.lower())
            if operation is None:
                continue
            operation["x-dncq-role"] = needed.value
            if scoped:
                operation["x-dncq-machine-scoped"] = True
            said = f"Role: {needed.value}" + (" (on its own machines)" if scoped else "") + "."
            operation["description"] = f"{operation.get('description', '')}\n\n{said}".strip()
    return document


def _rewrite(path: str, operation: dict[str, Any]) -> None:
    responses: dict[str, Any] = operation.setdefault("responses", {})
    responses.pop("422", None)  # FastAPI's validation error: dncq answers those with 400
    if not path.startswith("/api/cnc/"):
        responses["422"] = _error(_UNPROCESSABLE)
    for status, description in _ERRORS_BY_STATUS.items():
        responses[status] = _error(description)
    if "requestBody" in operation:
        responses["413"] = _error(_BODY_TOO_LARGE)
    if path.startswith(_RESOURCE_PREFIXES):
        for status, description in _RESOURCE_ERRORS.items():
            responses.setdefault(status, _error(description))
    if path.startswith(("/api/library/", "/api/inbox/")):
        responses.setdefault("413", _error(_TOO_LARGE))
    # A send of a library program that is not there; a listing by a machine nobody registered
    # that no job or backup holds (the other listings' prefixes give 404 already).
    if path in ("/api/jobs", "/api/backups"):
        responses.setdefault("404", _error(_RESOURCE_ERRORS["404"]))
    if path == "/api/jobs":  # a drip-feed run asked of a machine that has one not ended
        responses.setdefault("409", _error(_RESOURCE_ERRORS["409"]))
    if path == "/api/health":  # liveness without a key; the key adds the full report
        operation["security"] = [{}, *operation.get("security", [])]
    if path.startswith("/api/cnc/"):  # the contract's answer refusals with 200, dncq's own never
        _contract_errors_in_200(responses)


def _contract_errors_in_200(responses: dict[str, Any]) -> None:
    """The contract answers its errors with HTTP 200: beside the success JSON, or as JSON
    instead of a streamed file."""
    ok = responses.setdefault("200", {"description": "Successful Response"})
    content: dict[str, Any] = ok.setdefault("content", {})
    json = content.get("application/json")
    if json is None or not json.get("schema"):
        content["application/json"] = {"schema": ERROR_REF}
    else:
        json["schema"] = {"anyOf": [json["schema"], ERROR_REF]}
    ok["description"] = (ok.get("description") or "Successful Response") + \
        "; or the contract's error body, also with HTTP 200"


def _error(description: str) -> dict[str, Any]:
    return {"description": description, "content": {"application/json": {"schema": ERROR_REF}}}
