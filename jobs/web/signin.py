"""Signing in and out of the dashboard."""

from __future__ import annotations

import secrets
from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy.orm import Session

from jobs.settings import AuthMode, Settings
from jobs.web import principal as auth
from jobs.web import sessions
from jobs.web.deps import (
    ANONYMOUS,
    CSRF_FIELD,
    PageRoute,
    Refused,
    SessionDep,
    SettingsDep,
    Viewer,
    acting,
    render,
)
from jobs.web.refusals import audited_as

router = APIRouter(route_class=PageRoute)
# Before a session there is no session's token: the sign-in form's is kept in a cookie of
# its own, which another site's page cannot read, nor send along (SameSite=Strict).
SIGNIN_COOKIE = "dncq_signin"


def _safe_next(path: str | None) -> str:
    """Where to go after signing in: a path of this dashboard, never another site."""
    if not path or not path.startswith("/") or path.startswith("//") or "\\" in path:
        return "/"
    return path


def _with_cookie(response: Response, request: Request, token: str, max_age_s: float) -> None:
    response.set_cookie(sessions.COOKIE, token, max_age=int(max_age_s), httponly=True,
                        samesite="strict", secure=request.url.scheme == "https", path="/")


def _form(request: Request, *, next: str, error: str | None, name: str) -> Response:
    """The sign-in form, carrying the browser's sign-in token (a new one if it has none)."""
    token = request.cookies.get(SIGNIN_COOKIE) or secrets.token_urlsafe(sessions.TOKEN_BYTES)
    response = render(request, None, "signin.html", next=next, error=error, name=name,
                      signin_csrf=token)
    response.set_cookie(SIGNIN_COOKIE, token, httponly=True, samesite="strict",
                        secure=request.url.scheme == "https", path="/signin")
    return response


@router.get("/signin", response_class=HTMLResponse)
def signin_page(request: Request, session: SessionDep, settings: SettingsDep,
                next: str | None = None) -> Response:
    if settings.auth is AuthMode.NONE:  # nobody to sign in: an anonymous session at once
        begun = sessions.begin(session=session, settings=settings, user_name=ANONYMOUS,
                               address=request.client.host if request.client else None)
        response = RedirectResponse(_safe_next(next), status_code=303)
        _with_cookie(response, request, begun.token, settings.web_session_max_s)
        return response
    return _form(request, next=_safe_next(next), error=None, name="")


@router.post("/signin", response_class=HTMLResponse)
@audited_as("sign in")
def signin(request: Request, session: SessionDep, settings: SettingsDep,
           name: Annotated[str, Form(max_length=100)],
           password: Annotated[str, Form(max_length=1000)],
           next: Annotated[str, Form(max_length=2000)] = "/",
           csrf_token: Annotated[str, Form(alias=CSRF_FIELD, max_length=100)] = ""
           ) -> Response:
    # Else another site's page could sign a browser in as someone else (login CSRF), and
    # what its user then sends would be that someone's.
    kept = request.cookies.get(SIGNIN_COOKIE)
    if not (kept and secrets.compare_digest(csrf_token.encode(), kept.encode())):
        raise Refused("this sign-in form is out of date or did not come from this dashboard "
                      "(its CSRF token is missing or wrong): open the sign-in page again")
    address = request.client.host if request.client else None
    try:
        user = auth.authenticate(session=session, settings=settings, name=name,
                                 password=password, address=address)
    except auth.SignInRefused as exc:
        if exc.locked_now:  # once per lock-out: the refusals while it lasts add nothing
            _record_lock_out(session, settings, name=name, address=address,
                             until=exc.locked_until)
        session.commit()  # the failure counts, whatever is answered
        # 200: the form again with why; an error status is a console error in every browser
        return _form(request, next=_safe_next(next), error=exc.reason, name=name)
    begun = sessions.begin(session=session, settings=settings, user_name=user.name,
                           address=address)
    auth.record(session=session, principal=auth.principal_of(user), address=address,
                method="POST", path="/signin", status=303, action="sign in")
    response = RedirectResponse(_safe_next(next), status_code=303)
    _with_cookie(response, request, begun.token, settings.web_session_max_s)
    return response


def _record_lock_out(session: Session, settings: Settings, *, name: str, address: str | None,
                     until: datetime | None) -> None:
    """The audit trail's entry of a name locked out by failed sign-ins: by nobody known
    (`-`), on the name, from the address the last guess came from."""
    auth.record(session=session, principal=None, address=address, method="POST",
                path="/signin", status=401, action="lock out", target=name,
                detail={"failures": settings.signin_max_failures,
                        "until": until.isoformat() if until else None})


@router.post("/signout")
@audited_as("sign out")
def signout(request: Request, session: SessionDep,
            who: Annotated[Viewer, Depends(acting(auth.Role.VIEWER))]) -> Response:
    sessions.end(session=session, token=request.cookies.get(sessions.COOKIE))
    auth.record(session=session, principal=who.principal,
                address=request.client.host if request.client else None,
                method="POST", path="/signout", status=303, action="sign out")
    response = RedirectResponse("/signin", status_code=303)
    response.delete_cookie(sessions.COOKIE, path="/")
    return response
