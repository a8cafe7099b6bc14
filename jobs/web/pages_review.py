"""The review pages: the inbox (approve, reject), drip-feed runs (followed live, stopped),
and the library (versions, diff, approve)."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, Response, StreamingResponse

from jobs import db
from jobs.dnc import run_views, runs
from jobs.errors import ContractError, ErrorCode, library_status
from jobs.fleet import registry
from jobs.inbox import service as inbox
from jobs.inbox.models import InboxItem, InboxState
from jobs.inbox.views import item_view
from jobs.library import service as library
from jobs.library.models import VersionState
from jobs.library.views import program_view
from jobs.models import Run, RunState
from jobs.web.deps import (
    SIGNED_OUT_EVENT,
    PageRoute,
    RowId,
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
from jobs.web.principal import Role
from jobs.web.refusals import audited_as

router = APIRouter(route_class=PageRoute)

Operator = Annotated[Viewer, Depends(acting(Role.OPERATOR))]
Programmer = Annotated[Viewer, Depends(acting(Role.PROGRAMMER))]
RUN_EVENT_EVERY_S = 0.5
RUN_EVENTS_FOR_S = 3600.0


def _message(request: Request) -> str | None:
    return request.query_params.get("message")


# -- the inbox -------------------------------------------------------------------------

@router.get("/inbox", response_class=HTMLResponse)
def inbox_page(request: Request, session: SessionDep, who: ViewerDep, state: str = "pending",
               machine: str = "") -> Response:
    chosen = InboxState(state) if state in set(InboxState) else None
    items = inbox.list_items(session=session, machine_id=machine or None, state=chosen)
    # a mistyped id is said, with the one it was likely typed for
    registry.check_machine_filter(session=session, machine_id=machine or None,
                                  held_by=InboxItem.machine_id, found=items)
    return render(request, who, "inbox.html", items=[item_view(i) for i in items],
                  states=[s.value for s in InboxState], chosen={"state": state,
                                                               "machine": machine})


@router.get("/inbox/{item_id}", response_class=HTMLResponse)
def inbox_item(request: Request, session: SessionDep, settings: SettingsDep, who: ViewerDep,
               item_id: RowId) -> Response:
    item = inbox.get(session=session, item_id=item_id)
    try:
        diff = inbox.diff(session=session, settings=settings, item_id=item_id)
    except ContractError as exc:
        diff = f"{exc.status_msg}\n"
    return render(request, who, "inbox_item.html", item=item_view(item), diff=diff,
                  message=_message(request))


@router.post("/inbox/{item_id}/approve")
@audited_as("approve inbox item", status_of=library_status)
def approve_item(request: Request, session: SessionDep, settings: SettingsDep,
                 who: Programmer, item_id: RowId,
                 note: Annotated[str, Form(max_length=1000)] = "") -> Response:
    status = 200
    try:
        made = inbox.approve(session=session, settings=settings, item_id=item_id,
                             decided_by=who.principal.name, note=note)
        message = f"Approved as {made.program.path} v{made.number}."
    except inbox.Undecidable as exc:  # decided already: 409, as the API answers it
        message, status = f"Not approved: {exc.status_msg}", 409
    except ContractError as exc:  # as the API answers it: a missing item 404, too large 413
        message, status = f"Not approved: {exc.status_msg}", library_status(exc)
    audit(request, session, who, action="approve inbox item", target=str(item_id),
          status=status)
    return told(f"/inbox/{item_id}", message)


@router.post("/inbox/{item_id}/reject")
@audited_as("reject inbox item", status_of=library_status)
def reject_item(request: Request, session: SessionDep, who: Programmer, item_id: RowId,
                reason: Annotated[str, Form(max_length=1000)] = "") -> Response:
    status = 200
    try:
        inbox.reject(session=session, item_id=item_id, decided_by=who.principal.name,
                     reason=reason)
        message = "Rejected."
    except inbox.Undecidable as exc:  # decided already: 409, as the API answers it
        message, status = f"Not rejected: {exc.status_msg}", 409
    except ContractError as exc:  # as the API answers it: a missing item 404
        message, status = f"Not rejected: {exc.status_msg}", library_status(exc)
    audit(request, session, who, action="reject inbox item", target=str(item_id),
          status=status)
    return told(f"/inbox/{item_id}", message)


# -- drip-feed runs --------------------------------------------------------------------

@router.get("/runs", response_class=HTMLResponse)
def runs_page(request: Request, session: SessionDep, who: ViewerDep, state: str = "",
              machine: str = "") -> Response:
    found = run_views.list_runs(session=session, machine_id=machine or None,
                           state=RunState(state) if state in set(RunState) else None)
    # a mistyped id is said, with the one it was likely typed for
    registry.check_machine_filter(session=session, machine_id=machine or None,
                                  held_by=Run.machine_id, found=found)
    return render(request, who, "runs.html", runs=[run_views.view(r) for r in found],
                  states=[s.value for s in RunState], chosen={"state": state,
                                                             "machine": machine})


@router.get("/runs/{run_id}", response_class=HTMLResponse)
def run_page(request: Request, session: SessionDep, who: ViewerDep, run_id: RowId) -> Response:
    run = session.get(Run, run_id)
    if run is None:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no run {run_id}")
    return render(request, who, "run.html", run=run_views.view(run), message=_message(request))


@router.get("/runs/{run_id}/events")
def run_events(request: Request, settings: SettingsDep, who: ViewerDep,
               run_id: RowId) -> StreamingResponse:
    """Server-Sent Events: the run's line, and its rate in blocks per second."""
    url = settings.resolved_database_url
    signed_in = StillSignedIn(request, settings)

    def stream() -> Iterator[str]:
        started, last = time.monotonic(), ""
        yield "retry: 2000\n\n"
        while time.monotonic() - started < RUN_EVENTS_FOR_S:
            if not signed_in():
                yield SIGNED_OUT_EVENT
                return
            with db.session_scope(url) as session:
                run = session.get(Run, run_id)
                body: dict[str, Any] = run_views.view(run) if run is not None else {"state": "gone"}
            rate = None
            # As dncq run reckons it: the program's lines run from the run's start line, not
            # the lines sent (the header, and those the control holds ahead of its line).
            ran = body["line"] - (body["startLine"] - 1) if run is not None else 0
            if ran > 0 and body["startedAt"]:
                until = body["endedAt"] or body["updatedAt"]
                took_s = (until - body["startedAt"]).total_seconds()
                rate = round(ran / took_s, 1) if took_s > 0 else None
            text = json.dumps({**body, "rate": rate}, default=str)
            if text != last:
                yield f"data: {text}\n\n"
                last = text
            if body["state"] not in (RunState.QUEUED.value, RunState.RUNNING.value):
                yield "event: end\ndata: {}\n\n"
                return
            time.sleep(RUN_EVENT_EVERY_S)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-store"})


@router.post("/runs/{run_id}/stop")
@audited_as("stop run")
def stop_run(request: Request, session: SessionDep, settings: SettingsDep, who: Operator,
             run_id: RowId) -> Response:
    run = session.get(Run, run_id)
    if run is None:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no run {run_id}")
    # The stop is the job's, every run of it (as the API's): each of its machines counts.
    who.may_change(r.machine_id for r in run_views.of_job(session=session, job_id=run.job_id))
    n = runs.request_stop(session=session, settings=settings, job_id=run.job_id,
                          stopped_by=who.principal.name)
    audit(request, session, who, action="stop run", target=str(run_id))
    return told(f"/runs/{run_id}", f"Stopping {n} run(s).")


# -- the library -----------------------------------------------------------------------

@router.get("/library", response_class=HTMLResponse)
def library_page(request: Request, session: SessionDep, who: ViewerDep,
                 folder: str = "") -> Response:
    found = library.list_programs(session=session, folder=folder or None)
    return render(request, who, "library.html", programs=[program_view(p) for p in found],
                  folders=sorted({p.folder for p in library.list_programs(session=session)}),
                  chosen={"folder": folder})


@router.get("/library/p/{path:path}", response_class=HTMLResponse)
def library_program(request: Request, session: SessionDep, settings: SettingsDep,
                    who: ViewerDep, path: str, old: int = 0, new: int = 0) -> Response:
    folder, _, name = path.rpartition("/")
    program = library.find(session=session, folder=folder, name=name)
    body = program_view(program, versions=True)
    diff = None
    if old and new:
        try:
            diff = library.diff(session=session, settings=settings, folder=folder, name=name,
                                old=old, new=new)
        except ContractError as exc:
            diff = f"{exc.status_msg}\n"
    return render(request, who, "program.html", program=body, diff=diff, old=old, new=new,
                  message=_message(request))


_DECISIONS = {"approve": VersionState.APPROVED, "reject": VersionState.REJECTED}


def _decided_as(decision: object) -> str:
    """The audit action of a library decision (`decide library version` for neither)."""
    return f"{decision} library version" if decision in _DECISIONS else "decide library version"


@router.post("/library/p/{path:path}/decide")
@audited_as(lambda form: _decided_as(form.get("decision")))
def library_decide(request: Request, session: SessionDep, who: Programmer, path: str,
                   number: Annotated[int, Form()],
                   decision: Annotated[str, Form()]) -> Response:
    folder, _, name = path.rpartition("/")
    state = _DECISIONS.get(decision)
    status = 200
    if state is None:  # a form made by hand: nothing is decided for a word not understood
        message, status = f"Not decided: {decision!r} is neither approve nor reject.", 400
    else:
        try:
            library.decide(session=session, folder=folder, name=name, number=number,
                           state=state, decided_by=who.principal.name)
            message = f"v{number} {state.value}."
        except library.DecidedMeanwhile as exc:  # 409, as the API answers it
            message, status = f"Not decided: {exc.status_msg}. Their decision stands.", 409
        except ContractError as exc:  # as the API answers it: a missing version 404
            message, status = f"Not decided: {exc.status_msg}", library_status(exc)
    audit(request, session, who, action=_decided_as(decision),
          target=f"{path} v{number}", status=status)
    return told(f"/library/p/{path}", message)
