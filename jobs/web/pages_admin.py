"""The admin pages: users (added, changed, disabled, removed), named API keys (made, shown
once, revoked), the client addresses locked out (their lock-outs ended) and the audit trail
(filtered, paged, exported as CSV)."""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Annotated, Any
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, Response, StreamingResponse
from sqlalchemy.orm import Session

from jobs.errors import ContractError, resource_status
from jobs.models import utcnow
from jobs.web import principal as auth
from jobs.web import sessions
from jobs.web.deps import (
    PageRoute,
    Refused,
    SessionDep,
    Viewer,
    ViewerDep,
    acting,
    audit,
    get_settings,
    render,
    told,
)
from jobs.web.principal import Role
from jobs.web.refusals import audited_as

router = APIRouter(route_class=PageRoute)

Admin = Annotated[Viewer, Depends(acting(Role.ADMIN))]
AUDIT_PAGE = 100  # events on a page of the trail
CSV_LIMIT = 10_000  # events in one CSV export, as the API's
USERS = "/admin/users"
Text = Annotated[str, Form(max_length=1000)]


def _admin_reads(who: Viewer, what: str) -> None:
    """A page only admins read: refused (403) for every other role."""
    if not who.may(Role.ADMIN):
        raise Refused(f"the {what} page needs the admin role; you ({who.principal.name}) "
                      f"are {who.principal.role.with_article}")


def _machines(text: str) -> list[str] | None:
    """A form's machine list: ids separated by commas or spaces; empty or `all`: all."""
    ids = [m for m in text.replace(",", " ").split() if m]
    return None if not ids or ids == ["all"] else ids


class BadRole(ValueError):
    """A role that is none of dncq's: the API answers it 400, as any value it cannot parse."""


def _role(text: str) -> Role:
    if text not in set(Role):
        raise BadRole(f"a role is one of {', '.join(Role)}")
    return Role(text)


def _new_password(password: str, again: str) -> str:
    if password != again:
        raise ValueError("the two passwords differ")
    return password


def _not_myself(who: Viewer, name: str, doing: str) -> None:
    """An admin does not lock themself out by mistake: no removing, disabling or demoting
    the user signed in."""
    if who.principal.kind == "user" and who.principal.name == name:
        raise ValueError(f"you are signed in as {name}: {doing} it as another admin")


# -- users and keys -----------------------------------------------------------------------

def _users_page(request: Request, session: Session, who: Viewer, status: int = 200,
                **context: Any) -> Response:
    stored = {u.name for u in auth.list_users(session=session)}
    response = render(request, who, "users.html", status=status,
                      users=auth.list_users(session=session),
                      keys=auth.list_keys(session=session), roles=[r.value for r in Role],
                      admin_key_user=auth.ADMIN_USER not in stored, now=utcnow(),
                      lockouts=auth.counted_lockouts(session=session,
                                                     settings=get_settings(request)),
                      message=context.pop("message", request.query_params.get("message")),
                      **context)
    response.headers["Cache-Control"] = "no-store"  # a new key is on it, once
    return response


@router.get(USERS, response_class=HTMLResponse)
def users_page(request: Request, session: SessionDep, who: ViewerDep) -> Response:
    _admin_reads(who, "users")
    return _users_page(request, session, who)


@router.post(USERS)
@audited_as("add user")
def add_user(request: Request, session: SessionDep, who: Admin,
             name: Annotated[str, Form(max_length=100)], role: Annotated[str, Form()],
             password: Text, password_again: Text, machines: Text = "") -> Response:
    chosen = _machines(machines)
    detail = {"role": role, "machines": chosen}
    try:
        auth.add_user(session=session, name=name.strip(), role=_role(role), machines=chosen,
                      password=_new_password(password, password_again))
    except (ValueError, ContractError) as exc:
        session.rollback()
        audit(request, session, who, action="add user", target=name, status=_status(exc),
              detail=detail)
        return _users_page(request, session, who, error=f"User {name} not added: "
                           f"{_why(exc)}", form={"name": name, "role": role,
                                                 "machines": machines})
    sessions.end_all_of(session=session, user_name=name.strip())  # none of a former namesake
    audit(request, session, who, action="add user", target=name, detail=detail)
    return told(f"{USERS}/{name.strip()}", f"Added {name.strip()} ({role}).")


@router.get(USERS + "/{name}", response_class=HTMLResponse)
def user_page(request: Request, session: SessionDep, who: ViewerDep, name: str) -> Response:
    _admin_reads(who, "users")
    return render(request, who, "user.html", user=auth.stored_user(session=session, name=name),
                  roles=[r.value for r in Role], message=request.query_params.get("message"),
                  now=utcnow(),
                  myself=who.principal.kind == "user" and who.principal.name == name)


def _why(exc: Exception) -> str:
    return exc.status_msg or str(exc) if isinstance(exc, ContractError) else str(exc)


def _status(exc: Exception) -> int:
    """The status the API answers the same refusal with: a name taken 409, a role that is
    none 400, a value refused (a short password, a machine no one has, passwords that
    differ, the admin's own user demoted) 422."""
    if isinstance(exc, ContractError):
        return resource_status(exc)
    return 400 if isinstance(exc, BadRole) else 422


def _not_changed(request: Request, session: Session, who: Viewer, name: str, action: str,
                 exc: ValueError, detail: dict[str, Any] | None = None,
                 said: str = "Not changed") -> Response:
    """A change of a user refused by the page's own checks: recorded as the API's refusal
    of it, and back to the user's page saying why."""
    audit(request, session, who, action=action, target=name, status=_status(exc),
          detail=detail)
    return told(f"{USERS}/{name}", f"{said}: {exc}")


def _changed(request: Request, session: Session, who: Viewer, name: str, action: str,
             done: str, detail: dict[str, Any] | None = None, **change: Any) -> Response:
    """Change a user, record it, and go back to its page saying what happened."""
    auth.stored_user(session=session, name=name)  # 404 for a name that is not there
    try:
        auth.change_user(session=session, name=name, **change)
    except ValueError as exc:
        session.rollback()
        audit(request, session, who, action=action, target=name, status=_status(exc),
              detail=detail)
        return told(f"{USERS}/{name}", f"Not changed: {exc}")
    if change.get("disabled"):
        sessions.end_all_of(session=session, user_name=name)  # signed out everywhere now
    audit(request, session, who, action=action, target=name, detail=detail)
    return told(f"{USERS}/{name}", done)


@router.post(USERS + "/{name}/set")
@audited_as("change user")
def change_user(request: Request, session: SessionDep, who: Admin, name: str,
                role: Annotated[str, Form()], machines: Text = "") -> Response:
    chosen = _machines(machines)
    detail = {"role": role, "machines": chosen}
    try:
        new_role = _role(role)
        if new_role is not Role.ADMIN:
            _not_myself(who, name, "demote")
    except ValueError as exc:
        return _not_changed(request, session, who, name, "change user", exc, detail)
    return _changed(request, session, who, name, "change user",
                    f"{name} is now {new_role.with_article} on "
                    f"{', '.join(chosen) if chosen else 'every machine'}.",
                    detail=detail, role=new_role, machines=chosen)


@router.post(USERS + "/{name}/password")
@audited_as("set password")
def set_password(request: Request, session: SessionDep, who: Admin, name: str,
                 password: Text, password_again: Text) -> Response:
    try:
        _new_password(password, password_again)
    except ValueError as exc:
        return _not_changed(request, session, who, name, "set password", exc)
    return _changed(request, session, who, name, "set password",
                    f"New password set for {name}; any lock-out is ended.", password=password)


@router.post(USERS + "/{name}/disable")
@audited_as("disable user")
def disable_user(request: Request, session: SessionDep, who: Admin, name: str) -> Response:
    try:
        _not_myself(who, name, "disable")
    except ValueError as exc:
        return _not_changed(request, session, who, name, "disable user", exc)
    return _changed(request, session, who, name, "disable user",
                    f"{name} is disabled and signed out.", disabled=True)


@router.post(USERS + "/{name}/enable")
@audited_as("enable user")
def enable_user(request: Request, session: SessionDep, who: Admin, name: str) -> Response:
    return _changed(request, session, who, name, "enable user", f"{name} may sign in again.",
                    disabled=False)


@router.post(USERS + "/{name}/delete")
@audited_as("delete user")
def delete_user(request: Request, session: SessionDep, who: Admin, name: str) -> Response:
    try:
        _not_myself(who, name, "remove")
    except ValueError as exc:
        return _not_changed(request, session, who, name, "delete user", exc,
                            said="Not removed")
    auth.remove_user(session=session, name=name)
    sessions.end_all_of(session=session, user_name=name)
    audit(request, session, who, action="delete user", target=name)
    return told(USERS, f"Removed {name}; the audit trail keeps what it did.")


@router.post("/admin/keys")
@audited_as("add key")
def add_key(request: Request, session: SessionDep, who: Admin,
            name: Annotated[str, Form(max_length=100)], role: Annotated[str, Form()],
            machines: Text = "") -> Response:
    chosen = _machines(machines)
    detail = {"role": role, "machines": chosen}
    try:
        key, plain = auth.add_key(session=session, name=name.strip(), role=_role(role),
                                  machines=chosen, created_by=who.principal.name)
    except (ValueError, ContractError) as exc:
        session.rollback()
        audit(request, session, who, action="add key", target=name, status=_status(exc),
              detail=detail)
        return _users_page(request, session, who, key_error=f"Key {name} not made: "
                           f"{_why(exc)}", key_form={"name": name, "role": role,
                                                     "machines": machines})
    audit(request, session, who, action="add key", target=key.name, detail=detail)
    # the page itself, not a redirect: the key must never be in a URL or a second answer
    return _users_page(request, session, who, new_key={"name": key.name, "key": plain})


@router.post("/admin/keys/{name}/revoke")
@audited_as("revoke key")
def revoke_key(request: Request, session: SessionDep, who: Admin, name: str) -> Response:
    auth.revoke_key(session=session, name=name)
    audit(request, session, who, action="revoke key", target=name)
    return told(USERS, f"Key {name} is revoked: refused from now on.")


@router.post("/admin/lockouts/{address:path}/end")  # a path: an IPv6 row is its /64
@audited_as("lockouts.end")
def end_lockout(request: Request, session: SessionDep, who: Admin, address: str) -> Response:
    """End an address's lock-outs as `DELETE /api/lockouts/{address}` does: the API process
    serving the dashboard takes the address again at once, the others within 10 s."""
    try:
        ended = auth.end_lockout(session=session, address=address,
                                 kept=request.app.state.locked_addresses)
    except ContractError as exc:
        session.rollback()
        audit(request, session, who, action="lockouts.end", target=address,
              status=resource_status(exc))
        return told(USERS, f"No lock-out ended: {_why(exc)}.")
    row = ended[0].address
    audit(request, session, who, action="lockouts.end", target=row,
          detail=auth.ended_detail(ended))
    return told(USERS, f"Ended the lock-out of {row} ({', '.join(c.counted for c in ended)}) "
                       f"and forgot its failures.")


# -- the audit trail ----------------------------------------------------------------------

def _day(text: str, *, end: bool = False) -> datetime | None:
    """A form's date as the server's local midnight; `end`: the midnight after it."""
    try:
        day = datetime.fromisoformat(text).astimezone() if text else None
    except ValueError:
        return None
    return day + timedelta(days=1) if day is not None and end else day


def _filters(who: str, action: str, since: str, until: str) -> dict[str, Any]:
    return {"who": who or None, "action": action or None, "since": _day(since),
            "until": _day(until, end=True)}


@router.get("/admin/audit", response_class=HTMLResponse)
def audit_page(request: Request, session: SessionDep, me: ViewerDep, who: str = "",
               action: str = "", since: str = "", until: str = "", page: int = 1) -> Response:
    _admin_reads(me, "audit")
    page = max(1, page)
    found = auth.audit_events(session=session, limit=AUDIT_PAGE + 1,
                              offset=(page - 1) * AUDIT_PAGE,
                              **_filters(who, action, since, until))
    whos, actions = auth.audit_names(session=session)
    chosen = {"who": who, "action": action, "since": since, "until": until}
    query = {k: v for k, v in chosen.items() if v}
    return render(request, me, "audit.html", events=found[:AUDIT_PAGE], whos=whos,
                  actions=actions, chosen=chosen, page=page,
                  newer=f"?{urlencode({**query, 'page': page - 1})}" if page > 1 else None,
                  older=f"?{urlencode({**query, 'page': page + 1})}"
                  if len(found) > AUDIT_PAGE else None,
                  csv=f"/audit.csv?{urlencode(query)}" if query else "/audit.csv")


@router.get("/audit.csv")
def audit_csv(session: SessionDep, me: ViewerDep, who: str = "", action: str = "",
              since: str = "", until: str = "") -> StreamingResponse:
    """The trail (filtered as the page is) as CSV, newest first."""
    _admin_reads(me, "audit")
    found = auth.audit_events(session=session, limit=CSV_LIMIT,
                              **_filters(who, action, since, until))
    rows = list(auth.audit_csv(found))  # made now: the database session ends with this call
    return StreamingResponse(iter(rows), media_type="text/csv; charset=utf-8",
                             headers={"Content-Disposition":
                                      'attachment; filename="dncq-audit.csv"'})
