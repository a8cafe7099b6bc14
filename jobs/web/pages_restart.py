"""Restart a drip-feed run from a block: the point asked, its header previewed, then run.

The restart is planned as the API plans a `dnc_run` job's (`jobs.dnc.starting.plan`): the
preview is its dry run (the header lines and the start line, nothing started) and *Start*
submits a new run of the same stored program on the same machine. A point the scan cannot
be sure of is refused with its reason, and nothing starts.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy.orm import Session

from jobs.dnc import programs, run_views, runs, starting
from jobs.dnc.modal import MachineKind
from jobs.errors import ContractError, ErrorCode
from jobs.models import Run, RunState
from jobs.settings import Settings
from jobs.web.deps import (
    PageRoute,
    Refused,
    RowId,
    SessionDep,
    SettingsDep,
    Viewer,
    ViewerDep,
    acting,
    audit,
    render,
)
from jobs.web.principal import Role
from jobs.web.refusals import audited_as

router = APIRouter(route_class=PageRoute)

Operator = Annotated[Viewer, Depends(acting(Role.OPERATOR))]
Text = Annotated[str, Form(max_length=100)]
ENDED = (RunState.SUCCEEDED, RunState.STOPPED, RunState.FAILED)  # may be restarted
KINDS = ("block", "line", "tool")


def _run_to_restart(session: Session, who: Viewer, run_id: int) -> Run:
    """The run, when it has ended and the viewer is an operator allowed its machine."""
    run = session.get(Run, run_id)
    if run is None:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no run {run_id}")
    if not who.may(Role.OPERATOR):
        raise Refused(f"restarting a run needs the operator role; you ({who.principal.name})"
                      f" are {who.principal.role.with_article}")
    who.may_change([run.machine_id])
    return run


def _asked(kind: str, point: str, tool: str, machine_kind: str) -> starting.RestartAsked:
    """The restart point the form names; ValueError for one it cannot name."""
    point, tool = point.strip(), tool.strip()
    if kind not in KINDS:
        raise ValueError(f"restart from one of: {', '.join(KINDS)}")
    if not point:
        raise ValueError(f"give the {kind} to restart from (e.g. "
                         f"{ {'block': 'N1234', 'line': '48213', 'tool': 'T7'}[kind]})")
    kind_of = MachineKind(machine_kind) if machine_kind in set(MachineKind) else None
    if kind == "block":
        return starting.RestartAsked(from_block=point, machine_kind=kind_of)
    if kind == "tool":
        return starting.RestartAsked(from_tool=point, machine_kind=kind_of)
    if not point.isdigit() or int(point) < 1:
        raise ValueError(f"a line is a number from 1, not {point!r}")
    return starting.RestartAsked(from_line=int(point), from_tool=tool or None,
                                 machine_kind=kind_of)


def _page(request: Request, who: Viewer, run: Run, status: int = 200,
          **context: Any) -> HTMLResponse:
    return render(request, who, "restart.html", status=status, run=run_views.view(run),
                  kinds=KINDS, machine_kinds=[k.value for k in MachineKind], **context)


@router.get("/runs/{run_id}/restart", response_class=HTMLResponse)
def restart_page(request: Request, session: SessionDep, who: ViewerDep,
                 run_id: RowId) -> Response:
    run = _run_to_restart(session, who, run_id)
    return _page(request, who, run, form={"kind": "block", "point": run.restart_from or ""},
                 ended=run.state in ENDED)


def _plan(settings: Settings, run: Run, asked: starting.RestartAsked) -> runs.Restart:
    planned = starting.plan(settings, programs.info(settings, run.program_id), asked)
    assert planned is not None  # a point is always given here
    return planned


@router.post("/runs/{run_id}/restart", response_class=HTMLResponse)
@audited_as("restart run", previewed=True)
def restart_post(request: Request, session: SessionDep, settings: SettingsDep,
                 who: Operator, run_id: RowId, kind: Text = "block", point: Text = "",
                 tool: Text = "", machine_kind: Text = "", action: Text = "preview",
                 queue: Text = "") -> Response:
    """Preview the restart (a dry run: nothing starts) or start it, as the button says."""
    run = _run_to_restart(session, who, run_id)
    form = {"kind": kind, "point": point, "tool": tool, "machine_kind": machine_kind,
            "queue": queue}
    if run.state not in ENDED:
        if action == "start":  # 409, as the API answers a run asked of a machine still running
            audit(request, session, who, action="restart run", target=str(run_id),
                  status=409, detail=form)
        return _page(request, who, run, status=409, form=form, ended=False,
                     error=f"Run #{run.id} is {run.state.value}: only a run that has ended "
                           "is restarted")
    try:
        planned = _plan(settings, run, _asked(kind, point, tool, machine_kind))
    except (ContractError, ValueError) as exc:
        reason = exc.status_msg if isinstance(exc, ContractError) else f"cannot restart: {exc}"
        if action == "start":  # 422, as the page and the API's restart refuse the point
            audit(request, session, who, action="restart run", target=str(run_id),
                  status=422, detail=form)
        return _page(request, who, run, status=422, form=form, ended=True,
                     error=f"Not restarted: {reason}")
    if action != "start":
        return _page(request, who, run, form=form, ended=True, preview=planned)
    try:
        job = runs.submit(session=session, settings=settings, machine_ids=[run.machine_id],
                          program=programs.info(settings, run.program_id),
                          file_name=run.program_name, restart=planned,
                          created_by=who.principal.name, queue=queue == "on")
    except ContractError as exc:
        if exc.code is not ErrorCode.MACHINE_BUSY:
            raise
        audit(request, session, who, action="restart run", target=str(run_id),
              status=409, detail=form)
        return _page(request, who, run, status=409, form=form, ended=True, preview=planned,
                     error=f"Not restarted: {exc.status_msg}")
    audit(request, session, who, action="restart run", target=str(run_id),
          detail={**form, "job": job.id, "startLine": planned.start_line})
    started = run_views.of_job(session=session, job_id=job.id)
    return RedirectResponse(f"/runs/{started[0].id}" if started else f"/jobs/{job.id}",
                            status_code=303)
