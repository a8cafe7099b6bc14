"""The jobs pages: the list, one job's targets live (retry, cancel), and a new rollout
with its dry-run preview."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response, StreamingResponse
from pydantic import ValidationError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from jobs import db, job_views, rollout, service
from jobs.dnc import run_views, runs
from jobs.errors import (
    ContractError,
    ErrorCode,
    first_named,
    library_status,
    resource_status,
    validation_summary,
)
from jobs.fleet import registry
from jobs.job_options import JobOptions
from jobs.library import blobs, names
from jobs.library import service as library
from jobs.library.models import LibraryVersion
from jobs.models import JobKind, JobState, Target, TargetState
from jobs.run import job_ends
from jobs.settings import Settings
from jobs.web.deps import (
    SIGNED_OUT_EVENT,
    PageRoute,
    Refused,
    SessionDep,
    SettingsDep,
    StillSignedIn,
    Viewer,
    ViewerDep,
    acting,
    audit,
    render,
    told,
)
from jobs.web.principal import Role, refusal, role_for_job
from jobs.web.refusals import audited_as

router = APIRouter(route_class=PageRoute)

Programmer = Annotated[Viewer, Depends(acting(Role.PROGRAMMER))]
Reader = Annotated[Viewer, Depends(acting(Role.VIEWER))]  # the route checks the role itself
EVENT_EVERY_S = 1.0  # how often a followed job is read again
EVENTS_FOR_S = 3600.0  # a page left open is answered this long; the browser reconnects
KEEPALIVE_EVERY_S = 15.0
TARGETS_SHOWN = 500  # of a job's targets on its page, the first ones


def _parsed_time(text: str) -> datetime | None:
    """A form's day (or time) on the server's clock, the one the list shows, as the backups'
    and the audit trail's days are: not UTC's midnight."""
    try:
        return datetime.fromisoformat(text).astimezone() if text else None
    except ValueError:
        return None


@router.get("/jobs", response_class=HTMLResponse)
def job_list(request: Request, session: SessionDep, who: ViewerDep, state: str = "",
             kind: str = "", machine: str = "", since: str = "", until: str = "") -> Response:
    found = service.list_jobs(
        session=session, state=JobState(state) if state in set(JobState) else None,
        kind=JobKind(kind) if kind in set(JobKind) else None, machine_id=machine or None,
        since=_parsed_time(since), until=_parsed_time(until), limit=200)
    # a mistyped id is said, with the one it was likely typed for
    registry.check_machine_filter(session=session, machine_id=machine or None,
                                  held_by=Target.machine_id, found=found)
    return render(request, who, "jobs.html",
                  jobs=[job_views.view(session=session, job=j) for j in found],
                  states=[s.value for s in JobState], kinds=[k.value for k in JobKind],
                  chosen={"state": state, "kind": kind, "machine": machine, "since": since,
                          "until": until})


def _job_body(session: Any, job_id: str) -> dict[str, Any]:
    job = service.get_job(session=session, job_id=job_id)
    body = job_views.view(session=session, job=job,
                        page=job_views.TargetPage(limit=TARGETS_SHOWN))
    if job.kind is JobKind.DNC_RUN:
        body["runs"] = [run_views.view(r) for r in run_views.of_job(session=session, job_id=job_id)]
    body["finalCount"] = sum(body["counts"].get(s.value, 0) for s in TargetState if s.final)
    body["finished"] = job.state in (JobState.SUCCEEDED, JobState.FAILED,
                                     JobState.CANCELLED) and not any(
        t["state"] in ("pending", "running") for t in body["targets"])
    return body


@router.get("/jobs/{job_id}", response_class=HTMLResponse)
def job_page(request: Request, session: SessionDep, who: ViewerDep, job_id: str) -> Response:
    body = _job_body(session, job_id)
    return render(request, who, "job.html", job=body,
                  may_cancel=who.may(role_for_job(JobKind(body["kind"]))),
                  message=request.query_params.get("message"))


@router.get("/jobs/{job_id}/events")
def job_events(request: Request, settings: SettingsDep, who: ViewerDep,
               job_id: str) -> StreamingResponse:
    """Server-Sent Events: the job's summary and targets each time they change."""
    url = settings.resolved_database_url
    signed_in = StillSignedIn(request, settings)

    def stream() -> Iterator[str]:
        last, quiet_since, started = "", time.monotonic(), time.monotonic()
        yield "retry: 2000\n\n"
        while time.monotonic() - started < EVENTS_FOR_S:
            if not signed_in():
                yield SIGNED_OUT_EVENT
                return
            with db.session_scope(url) as session:
                body = _job_body(session, job_id)
            text = json.dumps(body, default=str)
            if text != last:
                yield f"data: {text}\n\n"
                last, quiet_since = text, time.monotonic()
            elif time.monotonic() - quiet_since > KEEPALIVE_EVERY_S:
                yield ": still here\n\n"
                quiet_since = time.monotonic()
            if body["finished"]:
                yield "event: end\ndata: {}\n\n"
                return
            time.sleep(EVENT_EVERY_S)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})


@router.post("/jobs/{job_id}/retry")
@audited_as("retry job")
def retry(request: Request, session: SessionDep, settings: SettingsDep, who: Programmer,
          job_id: str) -> Response:
    status = 200
    try:
        job = service.get_job(session=session, job_id=job_id)
        who.may_change(t.machine_id for t in job.targets)  # refused (403), not caught here
        n = service.retry_failed(session=session, job_id=job_id)
        message = f"{n} target(s) queued again."
    except ContractError as exc:  # as the API answers it: a missing job 404, else 409
        n, message, status = 0, f"Not retried: {exc.status_msg}", resource_status(exc)
    audit(request, session, who, action="retry job", target=job_id, detail={"retried": n},
          status=status)
    session.commit()
    if n:
        service.dispatch(settings=settings, job_id=job_id)
    return told(f"/jobs/{job_id}", message)


@router.post("/jobs/{job_id}/cancel")
@audited_as("cancel job")
def cancel(request: Request, session: SessionDep, settings: SettingsDep, who: Reader,
           job_id: str) -> Response:
    job = service.get_job(session=session, job_id=job_id)
    needed = role_for_job(job.kind)  # as the API's cancel: the kind's role
    if not who.may(needed):
        raise Refused(refusal(who.principal, needed, f"cancelling a {job.kind.value} job"))
    who.may_change(t.machine_id for t in job.targets)
    if job.kind is JobKind.DNC_RUN:  # a run that is not stopped would go on cutting
        n = runs.request_stop(session=session, settings=settings, job_id=job_id,
                              stopped_by=who.principal.name)
        message = f"Stopping {n} run(s)."
    else:
        n = service.cancel(session=session, job_id=job_id)
        message = f"{n} target(s) cancelled."
    audit(request, session, who, action="cancel job", target=job_id)
    session.commit()
    job_ends.announce(settings, job_id)  # a request waiting for the job may answer now
    return told(f"/jobs/{job_id}", message)


@router.post("/jobs/{job_id}/restore-replaced")
@audited_as("restore replaced files")
def restore_replaced(request: Request, session: SessionDep, settings: SettingsDep,
                     who: Programmer, job_id: str) -> Response:
    job = service.get_job(session=session, job_id=job_id)
    who.may_change(t.machine_id for t in job.targets)
    try:
        restore = rollout.restore_replaced(session=session, settings=settings, job=job,
                                           created_by=who.principal.name)
    except ContractError as exc:
        # as the API answers it: a job that replaced no file is 409, not a missing one
        replaced = any(t.replaced_payload_id for t in job.targets)
        audit(request, session, who, action="restore replaced files", target=job_id,
              status=resource_status(exc) if replaced else 409)
        return told(f"/jobs/{job_id}", f"Nothing put back: {exc.status_msg}")
    audit(request, session, who, action="restore replaced files", target=job_id,
          detail={"job": restore.id})
    return RedirectResponse(f"/jobs/{restore.id}", status_code=303)


# -- a new rollout ---------------------------------------------------------------------

FLEET_WIDE = 5  # a replace on more machines than this asks for a confirmation
UNKNOWN_NAMED = 20  # of the ids and tags nobody has, named in a refusal's audit entry


def _form_context(session: Any) -> dict[str, Any]:
    specs = registry.list_all(session=session)
    programs = [p for p in library.list_programs(session=session)
                if library.approved(p) is not None]
    return {"machines": specs, "tags": sorted({t for s in specs for t in s.tags}),
            "programs": [p.path for p in programs]}


@router.get("/rollout", response_class=HTMLResponse)
def rollout_page(request: Request, session: SessionDep, who: ViewerDep) -> Response:
    return render(request, who, "rollout.html", form={}, preview=None, error=None,
                  **_form_context(session))


class _Asked:
    """A rollout as the form asks it: the program's bytes, the machines, the options."""

    def __init__(self, form: dict[str, Any], ids: list[str], tags: list[str]) -> None:
        self.form = form
        self.selector = rollout.Selector(ids=ids, tags=tags, all=form.get("all") == "on")
        self.options = JobOptions(
            replace=form.get("replace") == "on", skip_identical=form.get("skip_identical") == "on",
            verify=form.get("verify") == "on",
            deliver_within=form.get("deliver_within") or None,
            abort_after_failures=_whole_number(form.get("abort_after_failures"),
                                               "abort after failures"))


def _rollout_status(exc: Exception, *, selecting: bool) -> int:
    """The status the job API answers a rollout refused before anything is queued with: the
    program missing 404 or not given 400 (as a send without content), an option it cannot
    read 400, a selection of no machine 422 (as one of machines nobody has)."""
    if not isinstance(exc, ContractError):
        return 400
    return 422 if selecting else library_status(exc)


def _whole_number(text: str | None, what: str) -> int | None:
    if not text:
        return None
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{what}: a whole number, not {text!r}") from None


def _program(session: Any, settings: Any, form: dict[str, Any]
             ) -> tuple[bytes, str, LibraryVersion | None]:
    """The bytes to send, their file name, and the library version they are, if one."""
    if form.get("source") == "library":
        if not form.get("library"):  # none is chosen for the user: the first may be wrong
            raise ContractError(ErrorCode.BAD_PARAMETER, "choose the library program to send")
        folder, name, number = names.split_reference(form["library"])
        chosen = library.for_send(session=session, folder=folder, name=name, number=number)
        return blobs.read_all(settings, chosen.sha256), form.get("file_name") or name, chosen
    uploaded = form.pop(_UPLOADED, None)
    if uploaded:  # kept once, and named in the form from then on: never sent back and forth
        form["upload_payload"] = service.store_payload(session=session, data=uploaded)
        data = uploaded
    elif form.get("upload_payload"):
        data = service.payload_data(session=session, payload_id=form["upload_payload"]) or b""
        if not data:
            form.pop("upload_payload")
            raise ContractError(ErrorCode.BAD_PARAMETER,
                                "the upload kept since the preview is gone: upload it again")
    else:
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            "choose a library program or upload a file")
    return data, form.get("file_name") or form.get("upload_name") or "PROGRAM", None


_UPLOADED = "_uploaded"  # the form's upload, this request's only


async def _read_form(request: Request) -> tuple[dict[str, Any], list[str], list[str]]:
    raw = await request.form()
    form: dict[str, Any] = {k: v for k, v in raw.items() if isinstance(v, str)}
    upload = raw.get("upload")
    if upload is not None and not isinstance(upload, str) and upload.filename:
        data = await upload.read()
        if data:
            form[_UPLOADED] = data
            form["upload_name"] = upload.filename
    ids = [v for v in raw.getlist("ids") if isinstance(v, str) and v]
    ids += [m.strip() for m in form.get("more_ids", "").replace(",", " ").split() if m.strip()]
    tags = [v for v in raw.getlist("tags") if isinstance(v, str) and v]
    form["ids"], form["tags"] = ids, tags
    return form, ids, tags


@router.post("/rollout", response_class=HTMLResponse)
@audited_as("start rollout", previewed=True)
async def rollout_post(request: Request, session: SessionDep, settings: SettingsDep,
                       who: Programmer) -> Response:
    """Preview (a dry run, nothing changed) or start, as the button pressed says."""
    form, ids, tags = await _read_form(request)
    # The database work runs beside the event loop, which must not wait on a write lock.
    return await run_in_threadpool(_rollout, request, session, settings, who, form, ids, tags)


def _rollout(request: Request, session: Session, settings: Settings, who: Viewer,
             form: dict[str, Any], ids: list[str], tags: list[str]) -> Response:
    context = _form_context(session)
    starting = form.get("action") == "start"
    selecting = False
    try:
        data, file_name, version = _program(session, settings, form)  # an upload kept first
        session.commit()  # the upload kept; no write held while the machines are asked
        asked = _Asked(form, ids, tags)
        selecting = True
        targets = rollout.select_targets(session=session, selector=asked.selector,
                                         file_name=file_name, dir_at_cnc=form.get("dir") or None,
                                         sub_dir=None)
    except (ContractError, ValidationError, ValueError) as exc:
        message = (exc.status_msg if isinstance(exc, ContractError)
                   else validation_summary(exc.errors()) if isinstance(exc, ValidationError)
                   else str(exc))
        if starting:
            audit(request, session, who, action="start rollout",
                  status=_rollout_status(exc, selecting=selecting))
        return render(request, who, "rollout.html", status=422, form=form, preview=None,
                      error=message, **context)
    who.may_change(t.machineID for t in targets)
    unknown = rollout.unknown(session=session, selector=asked.selector)
    wide = asked.options.replace and len(targets) > FLEET_WIDE
    unconfirmed = starting and wide and form.get("confirm") != "on"
    if not starting or unknown or unconfirmed:
        preview = rollout.dry_run(session=session, settings=settings, kind=JobKind.SEND,
                                  targets=targets, options=asked.options, data=data)
        # A start refused is recorded (422, as the API refuses a job naming unknown
        # machines, nothing queued) once the machines were asked: no write held meanwhile.
        if starting:
            audit(request, session, who, action="start rollout", status=422, detail=(
                {"unknown": first_named(unknown.ids + unknown.tags, UNKNOWN_NAMED)}
                if unknown else {"unconfirmed": len(targets)}))
        error = unknown.message() if unknown else (
            f"This replaces files on {len(targets)} machines: tick the confirmation to start."
            if unconfirmed else None)
        return render(request, who, "rollout.html", status=422 if starting else 200,
                      form=form, preview=preview, error=error, wide=wide,
                      file_name=file_name, size=len(data), **context)
    payload_id = service.store_payload(session=session, data=data)

    def recorded(job: Any) -> None:
        if version is not None:
            job.library_version_id = version.id
        audit(request, session, who, action="start rollout", target=job.id,
              detail={"file": file_name, "targets": len(targets)})

    job = rollout.submit(session=session, settings=settings, kind=JobKind.SEND,
                         targets=targets, options=asked.options, payload_id=payload_id,
                         created_by=who.principal.name, recorded=recorded)
    return RedirectResponse(f"/jobs/{job.id}", status_code=303)
