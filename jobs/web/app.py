"""Put the dashboard on an app: its pages at `/`, its files at `/static`, its error pages."""

from __future__ import annotations

from urllib.parse import quote

from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from jobs.web import (
    pages_admin,
    pages_backups,
    pages_fleet,
    pages_jobs,
    pages_restart,
    pages_review,
    pages_schedules,
    refusals,
    signin,
)
from jobs.web.deps import HERE, Refused, SignInNeeded, templates

STATIC_PATH = "/static"


def install(app: FastAPI) -> None:
    """Serve the dashboard beside the API of `app` (the API's paths are left as they are)."""
    for module in (signin, pages_fleet, pages_jobs, pages_backups, pages_review,
                   pages_restart, pages_schedules, pages_admin):
        app.include_router(module.router, include_in_schema=False)
    app.mount(STATIC_PATH, StaticFiles(directory=HERE / "static"), name="static")

    @app.exception_handler(SignInNeeded)
    async def sign_in_first(request: Request, exc: SignInNeeded) -> RedirectResponse:
        return RedirectResponse(f"/signin?next={quote(exc.next_path)}", status_code=303)

    @app.exception_handler(Refused)
    async def refused(request: Request, exc: Refused) -> HTMLResponse:
        me = getattr(request.state, "principal", None)
        if request.method == "POST":  # a change refused is in the trail, as the API's are
            await refusals.record(request, status=exc.status)
        return templates.TemplateResponse(request, "refused.html", {
            "me": me, "csrf": "", "refusal": exc.message,
            "title": "Sent already" if exc.status == 409 else None,
            "may": me.may if me else (lambda _: False)}, status_code=exc.status,
            headers={"Cache-Control": "no-store"})
