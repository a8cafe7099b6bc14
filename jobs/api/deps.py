"""Dependencies shared by the routes: settings, database session, who is asking and whether
their role allows it, machine files."""

from __future__ import annotations

import secrets
from collections.abc import Iterable, Iterator, Sequence
from typing import Annotated, Any

from fastapi import Depends, Query, Request, Security
from fastapi.security import APIKeyHeader, APIKeyQuery, HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from jobs.api import key_lockout
from jobs.api.errors import AuthError, RoleRefused
from jobs.auth import service as auth
from jobs.auth.passwords import KEY_PARAMETER
from jobs.auth.roles import ADMIN_KEY, ANONYMOUS, Principal, Role, machine_refusal, refusal
from jobs.db import session_scope
from jobs.errors import ErrorCode
from jobs.settings import Settings


def get_settings(request: Request) -> Settings:
    """The settings the app was made with."""
    return request.app.state.settings  # type: ignore[no-any-return]


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_session(settings: SettingsDep) -> Iterator[Session]:
    """A database session for one request, committed when the route returns."""
    with session_scope(settings.resolved_database_url) as session:
        yield session


# "function": committed before the answer goes out, so a client that has it sees the change.
SessionDep = Annotated[Session, Depends(get_session, scope="function")]

_key_header = APIKeyHeader(name="X-Api-Key", auto_error=False, description="dncq API key")
_key_bearer = HTTPBearer(auto_error=False, description="dncq API key, as a bearer token")
_key_query = APIKeyQuery(name=KEY_PARAMETER, auto_error=False, description="dncq API key")


def given_key(
    header_key: Annotated[str | None, Security(_key_header)],
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_key_bearer)],
    query_key: Annotated[str | None, Security(_key_query)],
) -> str | None:
    """The key a request came with: `X-Api-Key`, `Authorization: Bearer` (which OctoPrint
    takes too, and some of its clients send) or the `apikey` parameter."""
    return header_key or (bearer.credentials if bearer else None) or query_key


GivenKey = Annotated[str | None, Depends(given_key)]


def _same(given: str, expected: str) -> bool:
    return secrets.compare_digest(given.encode(), expected.encode())


def _principal_of_key(request: Request, given: str) -> Principal:
    """The admin key's or a named key's principal; 403 for a key nobody has, 401 revoked,
    429 for any key from an address locked out for wrong keys (`key_lockout`).

    `KEY@MACHINE` is a key scoped to one machine, for OctoPrint clients that keep only the
    host of the URL they are given (`request.state.key_machine` says which machine).
    """
    key_lockout.refuse_known_locked(request)
    expected: str | None = request.app.state.api_key
    request.state.key_machine = None
    key, at, machine = given.rpartition("@")
    scoped = bool(at and machine and key)
    # The admin key is compared in memory, asking no database (the limits a client asks
    # before every upload are answered without one): an address another API process locked
    # is refused here from the first other key it sends here, which finds the lock-out.
    if expected is not None:
        if _same(given, expected):
            return ADMIN_KEY
        if scoped and _same(key, expected):
            request.state.key_machine = machine
            return ADMIN_KEY
    settings: Settings = request.app.state.settings
    with session_scope(settings.resolved_database_url) as session:
        key_lockout.refuse_locked(request, session=session)
        found = auth.find_key(session=session, plain=given)
        if found is None and scoped:
            found = auth.find_key(session=session, plain=key)
            if found is not None:
                request.state.key_machine = machine
        if found is None:
            key_lockout.refuse_wrong_key(request, session=session, settings=settings)
        if found.revoked_at is not None:  # a key once given out, not a guess: not counted
            raise AuthError(401, ErrorCode.AUTH_INVALID, f"key {found.name} was revoked")
        return auth.key_principal(found)


def _resolved(request: Request, given: str | None) -> Principal | None:
    """Who asks: the dashboard's signed-in user, a key, nobody checked; None: no key given."""
    shown = getattr(request.state, "principal", None)
    if isinstance(shown, Principal):  # put there by the dashboard's session
        return shown
    if request.app.state.api_key is None:  # authentication switched off
        principal: Principal | None = ANONYMOUS
    else:
        principal = _principal_of_key(request, given) if given else None
    request.state.principal = principal
    return principal


def get_principal(request: Request, given: GivenKey) -> Principal:
    """The principal of the request: 401 without a key, 403 with a wrong one."""
    principal = _resolved(request, given)
    if principal is None:
        raise AuthError(401, ErrorCode.AUTH_MISSING)
    return principal


PrincipalDep = Annotated[Principal, Depends(get_principal)]


def recorded_as(principal: Principal, claimed: str) -> str:
    """Who a job, a version or a decision is recorded as made by: a named user's or key's
    own name; with the shared admin key (or no authentication) what the client says (the
    CLI sends its user's login), since the key names nobody."""
    return principal.name if principal.kind in ("user", "key") else claimed


def recorded_by(principal: PrincipalDep, by: Annotated[str, Query(
        max_length=100, description="Who does it, recorded (with the shared admin key; a "
                                    "named user's or key's own name is recorded instead)")]
                = "api") -> str:
    """`recorded_as` for routes that take a `by` query parameter."""
    return recorded_as(principal, by)


RecordedBy = Annotated[str, Depends(recorded_by)]


def require_api_key(principal: PrincipalDep) -> None:
    """401 without a key, 403 with a wrong one; nothing when auth is switched off."""


def optional_principal(request: Request, given: GivenKey) -> Principal | None:
    """The principal when a key came (or auth is off); None without one; 403 when wrong."""
    return _resolved(request, given)


def optional_api_key(principal: Annotated[Principal | None, Depends(optional_principal)]) -> bool:
    """Whether the caller may see details: a right key, or auth switched off; 403 when wrong."""
    return principal is not None


KeyGivenDep = Annotated[bool, Depends(optional_api_key)]


def key_machine(request: Request) -> str | None:
    """The machine a machine-scoped key (`KEY@MACHINE`) names, if the request used one."""
    return getattr(request.state, "key_machine", None)


class RoleCheck:
    """The dependency `requires` makes: the role a route needs, and its audit action.

    Attributes:
        role: the least role that may call the route.
        scoped: the route changes the machine its path (`machine_id`) or query
            (`machineID`) names: a principal with a machine list must have it there.
        action: the audit trail's name of what the route does (`machines.put`).
        by_route: the route refuses itself, naming the role of what it is asked (a job's
            kind), so that a refusal names the role needed; `role` is the least of those,
            and a principal below it is refused before the body (`refuse_below_least`).
        least_what: what the refusal below the least role names (`a job of any kind`).
    """

    def __init__(self, role: Role, *, scoped: bool, action: str | None,
                 by_route: bool = False, least_what: str = "this") -> None:
        self.role, self.scoped, self.action, self.by_route = role, scoped, action, by_route
        self.least_what = least_what

    def __call__(self, request: Request, principal: PrincipalDep) -> Principal:
        if not self.by_route and not principal.may(self.role):
            raise RoleRefused(refusal(principal, self.role))
        if self.scoped:
            machine = request.path_params.get("machine_id") or \
                request.query_params.get("machineID")
            if machine is not None:
                check_machines(principal, [machine])
        return principal

    def refuse_below_least(self, principal: Principal) -> None:
        """403 when the principal's role is below even the least `role`: whatever the body
        asks, the route would refuse it, so it is refused unread."""
        if not principal.may(self.role):
            raise RoleRefused(refusal(principal, self.role, self.least_what))

    def __repr__(self) -> str:
        return f"requires({self.role.value}{', scoped' if self.scoped else ''})"


def requires(role: Role, *, scoped: bool = False, action: str | None = None,
             by_route: bool = False, least_what: str = "this") -> Any:
    """A dependency: 403 with a clear message unless the principal's role includes `role`.

    Give it in a route's `dependencies=[...]`, or as a parameter's default
    (`principal: Annotated[Principal, requires(Role.OPERATOR)]`) to have the principal.
    `scoped`: the machine the request names must be one of the principal's.
    `by_route`: the route checks the role itself, first (see `RoleCheck`); a principal
    below `role` is refused before a body, naming `least_what`.
    """
    return Depends(RoleCheck(role, scoped=scoped, action=action, by_route=by_route,
                             least_what=least_what))


def role_checks(route: Any) -> list[RoleCheck]:
    """The role checks a route declares (`requires(...)`), its own and its routers'."""
    dependant = getattr(route, "dependant", None)  # an APIRoute, or FastAPI's RouteContext
    if dependant is None:
        return []
    found: list[RoleCheck] = []
    stack = list(dependant.dependencies)
    while stack:
        dependant = stack.pop()
        if isinstance(dependant.call, RoleCheck):
            found.append(dependant.call)
        stack.extend(dependant.dependencies)
    return found


async def authorized_before_body(request: Request, checks: Sequence[RoleCheck]) -> None:
    """401/403 for a request without a right key, or whose role a check refuses, before the
    route's body is read: FastAPI reads and parses a body before it runs the dependencies,
    and 20 MB of JSON from a client without any key took 500 MB and 6 s to parse for its
    401. The principal found is kept on the request, for the dependencies that ask again.
    """
    given = given_key(await _key_header(request), await _key_bearer(request),
                      await _key_query(request))
    principal = await run_in_threadpool(get_principal, request, given)  # a named key: a query
    for check in checks:
        if check.by_route:  # the kind's role is the route's, once the body is read
            check.refuse_below_least(principal)
        check(request, principal)


def check_machines(principal: Principal, machine_ids: Iterable[str]) -> None:
    """403 naming the machines outside the principal's list, if any are."""
    outside = [m for m in dict.fromkeys(machine_ids) if not principal.may_touch(m)]
    if outside:
        raise RoleRefused(machine_refusal(principal, outside))


def note_target(request: Request, target: str | None, **detail: Any) -> None:
    """What the audit trail records as the request's target (and a few details)."""
    request.state.audit_target = target
    if detail:
        request.state.audit_detail = detail
