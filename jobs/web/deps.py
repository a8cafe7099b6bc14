"""What every page needs: the signed-in principal, the CSRF check, roles, and rendering."""

from __future__ import annotations

import time
from collections.abc import Callable, Coroutine, Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlencode
from zoneinfo import ZoneInfo

from fastapi import Depends, Request, Response
from fastapi import Path as PathPart
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, RedirectResponse
from fastapi.routing import APIRoute
from fastapi.templating import Jinja2Templates
from markupsafe import Markup
from sqlalchemy.orm import Session
from starlette.datastructures import URL

from jobs import fire_times
from jobs.auth.passwords import is_key_parameter
from jobs.auth.roles import machine_refusal
from jobs.db import session_scope
from jobs.errors import NOT_FOUND_CODES, ContractError
from jobs.local_times import local_parts, local_text
from jobs.settings import AuthMode, Settings
from jobs.web import once, refusals, sessions
from jobs.web import principal as auth
from jobs.web.models import WebSession
from jobs.web.wrapping import breakable

HERE = Path(__file__).parent
templates = Jinja2Templates(directory=HERE / "templates")
CSRF_FIELD = "csrf_token"
CSRF_HEADER = "X-CSRF-Token"
ANONYMOUS = "anonymous"  # the principal with authentication off (DNCQ_AUTH=none)


class SignInNeeded(Exception):
    """No live session: the browser is sent to the sign-in page."""

    def __init__(self, next_path: str) -> None:
        super().__init__(next_path)
        self.next_path = next_path


RowId = Annotated[int, PathPart(ge=1, le=2**63 - 1)]
"""A row's number in a page's address: a BIGINT, so that a larger one is a bad parameter
(400) rather than the database's overflow (500)."""


class Refused(Exception):
    """A request the principal may not make, or one without its CSRF token (403); a form
    sent twice (409)."""

    def __init__(self, message: str, *, status: int = 403) -> None:
        super().__init__(message)
        self.message, self.status = message, status


NOT_FOUND = NOT_FOUND_CODES


def _page_status(refusal: ContractError) -> int:
    """The HTTP status of a page that says a service's `refusal`."""
    if refusal.code in NOT_FOUND:
        return 404
    return 503 if refusal.transient else 400  # a machine's 20006 that will come again: 400


class PageRoute(APIRoute):
    """A dashboard route: a service's refusal is a page that says it (the API's contract
    answers it as JSON with HTTP 200, which a browser would show as text), with the HTTP
    status of the refusal: 404 for what does not exist, 503 for a machine that cannot be
    reached now (the failures a batch retries), 400 for the rest. A form's refusal is
    recorded in the audit trail with the API's status for it (`refusals`)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        """The route's handler, with refusals made pages."""
        handler = super().get_route_handler()

        async def page(request: Request) -> Response:
            try:
                return await handler(request)
            except ContractError as exc:
                await refusals.record_refused(request, exc)  # a form's, as the API's are
                me = getattr(request.state, "principal", None)
                return templates.TemplateResponse(request, "refused.html", {
                    "me": me, "csrf": "", "may": me.may if me else (lambda _: False),
                    "title": "Not found" if exc.code in NOT_FOUND else "Not done",
                    "refusal": f"{int(exc.code)} {exc.status_msg or exc.code.name}"},
                    status_code=_page_status(exc),
                    headers={"Cache-Control": "no-store"})

        return page


def get_settings(request: Request) -> Settings:
    """The settings the app was made with."""
    return request.app.state.settings  # type: ignore[no-any-return]


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_session(request: Request, settings: SettingsDep) -> Iterator[Session]:
    """A database session for one page, committed when the page is made (a refusal's page
    keeps nothing of what its route did before it: `refusals`)."""
    with session_scope(settings.resolved_database_url) as session:
        request.state.page_session = session
        yield session


SessionDep = Annotated[Session, Depends(get_session, scope="function")]


@dataclass(frozen=True)
class Viewer:
    """Who is looking at a page: their principal and their browser session."""

    principal: auth.Principal
    web: WebSession

    def may(self, needed: auth.Role) -> bool:
        """Whether the role includes `needed`."""
        return self.principal.may(needed)

    def may_change(self, machine_ids: Iterable[str]) -> None:
        """Refused (403) naming the machines outside the principal's list, if any are: as
        the API refuses them (`jobs.api.deps.check_machines`)."""
        outside = [m for m in dict.fromkeys(machine_ids) if not self.principal.may_touch(m)]
        if outside:
            raise Refused(machine_refusal(self.principal, outside))


def _signed_in(request: Request, session: Session, settings: Settings) -> Viewer | None:
    row = sessions.find(session=session, settings=settings,
                        token=request.cookies.get(sessions.COOKIE))
    if row is None:
        return None
    if settings.auth is AuthMode.NONE and row.user_name == ANONYMOUS:
        return Viewer(auth.Principal(ANONYMOUS, "none", auth.Role.ADMIN), row)
    user = auth.user_named(session=session, name=row.user_name)
    if user is None or user.disabled:
        session.delete(row)
        return None
    return Viewer(auth.principal_of(user), row)


def viewer(request: Request, session: SessionDep, settings: SettingsDep) -> Viewer:
    """The signed-in viewer of a page; SignInNeeded sends the browser to sign in."""
    found = _signed_in(request, session, settings)
    if found is None:
        session.commit()  # an expired session's removal stays, whatever is answered
        raise SignInNeeded(_page_asked(request))
    request.state.principal = found.principal  # what the API's dependencies read
    return found


def _page_asked(request: Request) -> str:
    """The page to show after signing in: the one asked for, query and all; for a form
    sent after the session ended, the page it was sent from (a form's address is no page).
    An API key in its query is left out: it would stay in the address bar and history."""
    if request.method == "GET":
        url = request.url
    else:
        url = URL(request.headers.get("referer", "/"))
        if url.netloc and url.netloc != request.url.netloc:
            return "/"
    query = "&".join(p for p in url.query.split("&") if not is_key_parameter(p.partition("=")[0]))
    return url.path + (f"?{query}" if query else "")


ViewerDep = Annotated[Viewer, Depends(viewer)]

SESSION_RECHECK_S = 10.0  # a live stream looks this often whether its viewer is signed in
SIGNED_OUT_EVENT = "event: signedout\ndata: {}\n\n"  # the page reloads to the sign-in


class StillSignedIn:
    """Whether a live stream's viewer is still signed in: asked at every step, looked up
    every SESSION_RECHECK_S, so that a stream ends soon after its session expires, is
    signed out, or its user is disabled or removed, instead of running on for the hour."""

    def __init__(self, request: Request, settings: Settings) -> None:
        self.request, self.settings = request, settings
        self._checked = time.monotonic()  # the request itself was just let in

    def __call__(self) -> bool:
        if time.monotonic() - self._checked < SESSION_RECHECK_S:
            return True
        self._checked = time.monotonic()
        with session_scope(self.settings.resolved_database_url) as session:
            return _signed_in(self.request, session, self.settings) is not None


def acting(needed: auth.Role) -> Callable[..., Coroutine[Any, Any, Viewer]]:
    """A dependency for a state-changing request: the CSRF token, then the role (403)."""

    async def check(request: Request, who: ViewerDep, settings: SettingsDep) -> Viewer:
        given = request.headers.get(CSRF_HEADER)
        form_key: Any = None
        if given is None and request.headers.get("content-type", "").startswith(
                ("application/x-www-form-urlencoded", "multipart/form-data")):
            form = await request.form()
            value = form.get(CSRF_FIELD)
            given = value if isinstance(value, str) else None
            form_key = form.get(once.FIELD) if form.get("action") != "preview" else None
        if not sessions.csrf_matches(who.web, given):
            raise Refused("this form is out of date or did not come from this dashboard "
                          "(its CSRF token is missing or wrong): reload the page and try again")
        if not who.may(needed):
            raise Refused(f"this needs the {needed.value} role; you ({who.principal.name}) "
                          f"are {_article(who.principal.role.value)} {who.principal.role.value}")
        if isinstance(form_key, str) and form_key and not await run_in_threadpool(
                once.claim, settings.resolved_database_url, form_key):
            raise Refused("this form was sent already (a second click, or the page sent "
                          "again from the browser's history): nothing was started a second "
                          "time. Jobs and Runs show what the first did.", status=409)
        return who

    return check


def _article(word: str) -> str:
    return "an" if word[0] in "aeiou" else "a"


def audit(request: Request, session: Session, who: Viewer, *, action: str,
          target: str | None = None, status: int = 200,
          detail: dict[str, Any] | None = None) -> None:
    """Record a state-changing action of the dashboard in the audit trail."""
    auth.record(session=session, principal=who.principal,
                address=request.client.host if request.client else None,
                method=request.method, path=request.url.path, status=status, action=action,
                target=target, detail=detail)


def said(exc: ContractError) -> str:
    """A refusal as a page says it: `142 Path exists. (//CNC_MEM/O0077)`."""
    body = exc.body()
    detail = body.get("statusMsg")
    return f"{body['errorCode']} {body['errorMsg']}" + (f" ({detail})" if detail else "")


def told(path: str, message: str) -> RedirectResponse:
    """Back to `path` after a form, saying what happened there."""
    return RedirectResponse(f"{path}?{urlencode({'message': message})}", status_code=303)


def when(value: datetime | None, seconds: bool = True) -> Markup | str:
    """A time as the pages show it: on the server's clock, naming its zone as the CLI does
    (`2026-12-06 03:40:12 CET`); a list's to the minute, as the CLI's lists (`seconds`
    False), which keeps its columns narrow enough for an upright tablet."""
    if value is None:
        return "—"
    return _time_element(value, *local_parts(value, seconds=seconds))


def in_zone(value: datetime | None, zone: str) -> Markup | str:
    """A schedule's time as it is said: in the schedule's own zone, named (its cron is read
    in that zone: 02:00 Europe/Berlin, not the server's 01:00), and in the hour the clocks
    repeat, which pass (02:00 CEST, then 02:00 CET)."""
    if value is None:
        return "—"
    date, _, clock = fire_times.on_the_clock(value, ZoneInfo(zone)).partition(" ")
    return _time_element(value, date, f"{clock} {zone}")


def when_text(value: datetime | None) -> str:
    """`when` as plain text, for where no markup may go (a select's option)."""
    return local_text(value, seconds=True) if value is not None else "—"


def _time_element(value: datetime, date: str, clock: str) -> Markup:
    """A `<time>` whose date and clock each stay whole on a line (`class="when"`): a narrow
    cell broke `2026-12-` from `06`. It may wrap between the two."""
    instant = (value if value.tzinfo else value.replace(tzinfo=UTC)).astimezone(UTC)
    return Markup('<time class="when" datetime="%s"><span>%s</span> <span>%s</span></time>'
                  ) % (instant.isoformat(timespec="seconds"), date, clock)


def stamp(value: float | None, seconds: bool = True) -> Markup | str:
    """POSIX seconds (a file's date) as the pages show a time."""
    return when(datetime.fromtimestamp(value, UTC), seconds) if value is not None else "—"


def size(value: int | None) -> str:
    """A byte count as people read it, in units of 1,024 named so (as the CLI names them)."""
    if value is None:
        return "—"
    amount = float(value)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if amount < 1024 or unit == "TiB":
            return f"{amount:.0f} {unit}" if unit == "B" else f"{amount:.1f} {unit}"
        amount /= 1024
    return f"{value} B"


templates.env.filters["when"] = when
templates.env.filters["when_text"] = when_text
templates.env.filters["in_zone"] = in_zone
templates.env.filters["size"] = size
templates.env.filters["stamp"] = stamp
templates.env.filters["breakable"] = breakable
templates.env.globals["Role"] = auth.Role
templates.env.globals["form_key"] = once.new_key


def render(request: Request, who: Viewer | None, template: str, status: int = 200,
           **context: Any) -> HTMLResponse:
    """The page `template` with the viewer, their CSRF token and roles in its context.

    Never kept by the browser (`no-store`): Back after *Sign out* asks again and gets the
    sign-in, not the signed-in page, and a page shown is never an old one."""
    return templates.TemplateResponse(request, template, {
        "me": who.principal if who else None, "csrf": who.web.csrf_token if who else "",
        "may": (who.may if who else (lambda _: False)), **context},
        status_code=status, headers={"Cache-Control": "no-store"})
