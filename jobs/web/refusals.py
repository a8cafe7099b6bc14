"""A dashboard form refused is in the audit trail, as the API's are: under the action its
route records, with the HTTP status the API answers the same refusal with.

A route names its action with `@audited_as`, its refusals by the role, the CSRF token or a
second sending too; one that does not is recorded as `dashboard <route name>`. Read-only
pages (GET) are never recorded.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from fastapi import Request
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import FormData

from jobs.db import session_scope
from jobs.errors import ContractError, resource_status
from jobs.web import principal as auth

Endpoint = TypeVar("Endpoint", bound=Callable[..., Any])


@dataclass(frozen=True)
class Audited:
    """How a route's refusals are recorded."""

    # as the route's own entries name it (`stop run`), or named by the form sent
    action: str | Callable[[FormData], str]
    status_of: Callable[[ContractError], int] = resource_status  # the API's status for it
    previewed: bool = False  # a form whose action is not `start` is a dry run: not recorded

    async def action_of(self, request: Request) -> str:
        """The action `request` is recorded as."""
        return self.action if isinstance(self.action, str) else self.action(await request.form())


_DECLARED: dict[Callable[..., Any], Audited] = {}


def audited_as(action: str | Callable[[FormData], str], *,
               status_of: Callable[[ContractError], int] = resource_status,
               previewed: bool = False) -> Callable[[Endpoint], Endpoint]:
    """Declare the audit action of a form's route, and the API's status for its refusals
    (`resource_status` for dncq's own resources, `library_status` for programs and files).
    `action` may be a function of the form, for a route whose action its form names."""
    def declare(endpoint: Endpoint) -> Endpoint:
        _DECLARED[endpoint] = Audited(action, status_of, previewed)
        return endpoint

    return declare


def declared(request: Request) -> Audited:
    """The declaration of the route that took `request`, or the default one."""
    found = _DECLARED.get(getattr(request.scope.get("route"), "endpoint", None))  # type: ignore[arg-type]
    return found or Audited(route_named(request))


def route_named(request: Request) -> str:
    """`dashboard stop run`: the action of a route by its name."""
    return f"dashboard {getattr(request.scope.get('route'), 'name', 'form')}".replace("_", " ")


async def record_refused(request: Request, refusal: ContractError) -> None:
    """Undo what the form's route did before `refusal` (as the API's answer does), and
    record the refusal in the page's session, which is committed before the page is sent;
    unless the request is a read or a dry run."""
    audited = declared(request)
    if request.method == "GET":
        return
    if audited.previewed and (await request.form()).get("action") != "start":
        return
    session = getattr(request.state, "page_session", None)
    await run_in_threadpool(_write, request, status=audited.status_of(refusal),
                            action=await audited.action_of(request), session=session)


async def record(request: Request, *, status: int) -> None:
    """Record a form refused before its route ran (its role, its CSRF token, sent twice)
    under the route's action, in a session of its own (the page's ended with the refusal)."""
    action = await declared(request).action_of(request)
    await run_in_threadpool(_write, request, status=status, action=action)


def _write(request: Request, *, status: int, action: str,
           session: Session | None = None) -> None:
    """One entry: who sent the form, if anyone was recognised, and what it would change."""
    if session is not None:
        session.rollback()
        _add(request, session, status, action)
        return
    with session_scope(request.app.state.settings.resolved_database_url) as own:
        _add(request, own, status, action)


def _add(request: Request, session: Session, status: int, action: str) -> None:
    principal = getattr(request.state, "principal", None)
    params = list(request.path_params.values())
    auth.record(session=session,
                principal=principal if isinstance(principal, auth.Principal) else None,
                address=request.client.host if request.client else None,
                method=request.method, path=request.url.path, status=status,
                action=action, target=str(params[0]) if params else None)
