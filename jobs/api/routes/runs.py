"""Drip-feed runs: store a program, start a run (a `dnc_run` job), stop it, the run history."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Query, Request
from sqlalchemy.orm import Session

from jobs import job_views, rollout, service
from jobs.api.deps import (
    PrincipalDep,
    RecordedBy,
    SessionDep,
    SettingsDep,
    check_machines,
    requires,
)
from jobs.api.errors import CodedHTTPError, library_errors, refused_whole, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.dnc import programs, run_views, runs, starting
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import paths, registry
from jobs.library import names
from jobs.library import service as library_service
from jobs.models import Run, RunState
from jobs.settings import Settings

router = APIRouter(tags=["runs"], route_class=CheckedRoute)

PROGRAMS_PATH = "/api/programs"


@router.post(
    PROGRAMS_PATH, status_code=201,
    summary="Store a program for drip-feed runs (the raw body, any size)",
    openapi_extra={"requestBody": {"content": {"application/octet-stream": {}},
                                   "required": True}},
    dependencies=[requires(Role.OPERATOR, action="programs.store")],
)
async def store_program(request: Request, settings: SettingsDep) -> dict[str, Any]:
    stored = await programs.store_stream(settings, request.stream())
    return stored.view()


@router.get(PROGRAMS_PATH + "/{program_id}", summary="A stored program's size and lines",
            dependencies=[requires(Role.VIEWER)])
def program_info(settings: SettingsDep, program_id: str) -> dict[str, Any]:
    with resource_errors():
        return programs.info(settings, program_id).view()


def submit_run(*, session: Session, settings: Settings, program: str | None,
               library: str | None, library_version: int | None,
               file_name: str | None, machines: rollout.Selector | None,
               targets: list[dict[str, Any]] | None, restart: starting.RestartAsked,
               dry_run: bool, created_by: str, queue: bool = False) -> dict[str, Any]:
    """`POST /api/jobs` with kind `dnc_run`: one run per selected machine."""
    if library and program:
        raise HTTPException(422, detail="give program or library, not both")
    if library:  # the library version's blob is the stored program: no copy
        with library_errors():
            folder, name, number = names.split_reference(library)
            chosen = library_service.for_send(session=session, folder=folder, name=name,
                                              number=number or library_version)
        program, file_name = chosen.sha256, file_name or name
    if not program:
        raise HTTPException(422, detail="a dnc_run job names its program: `program`, the id "
                                        "POST /api/programs answered, or `library`")
    chosen_ids = machine_ids(session, machines, targets)
    with library_errors():  # an id that is no SHA-256 is a bad reference (400), not a conflict
        stored = programs.info(settings, program)
    if (why := stored.refusal()) is not None:
        raise refused_whole(ContractError(ErrorCode.BAD_PARAMETER, why))
    try:
        plan = starting.plan(settings, stored, restart)
    except ContractError as exc:
        raise refused_whole(exc) from None
    name = file_name or program[:12]
    with library_errors():  # what the control is told the program is called: 400 else
        paths.check_name(name)
    if dry_run:
        return {"dryRun": True, "program": stored.view(), "fileName": name,
                "machines": chosen_ids, "startLine": plan.start_line if plan else 1,
                "header": plan.header if plan else []}
    with resource_errors():  # a machine with a run not ended: 409
        job = runs.submit(session=session, settings=settings, machine_ids=chosen_ids,
                          program=stored, file_name=name, restart=plan,
                          created_by=created_by, queue=queue)
    return job_view(session=session, job_id=job.id)


def machine_ids(session: Session, machines: rollout.Selector | None,
                targets: list[dict[str, Any]] | None) -> list[str]:
    """The machines a run job is for: its targets', or those its selector picks (422 for
    ids or tags no machine has, or for none at all), each once."""
    if targets is not None:  # checked as a selector of their ids: one way to be refused
        machines = rollout.Selector(ids=[service.TargetIn.parse(t).machineID for t in targets])
    if machines is None:
        raise HTTPException(422, detail="give machines (ids, tags or all) or targets")
    found = rollout.unknown(session=session, selector=machines)
    if found:
        raise refused_whole(rollout.refuse_unknown(found))
    try:
        chosen = rollout.select_targets(session=session, selector=machines, file_name=None,
                                        dir_at_cnc=None, sub_dir=None)
    except ContractError as exc:
        raise refused_whole(exc) from None
    return [t.machineID for t in chosen]


def job_view(*, session: Session, job_id: str, page: job_views.TargetPage | None = None
             ) -> dict[str, Any]:
    """A dnc_run job as `GET /api/jobs/{id}` shows it: the job, and each run's line."""
    job = service.get_job(session=session, job_id=job_id)
    body = job_views.view(session=session, job=job, page=page or job_views.TargetPage())
    body["runs"] = [run_views.view(r) for r in run_views.of_job(session=session, job_id=job_id)]
    return body


@router.post("/api/jobs/{job_id}/stop",
             summary="Stop a drip-feed run: the machine is reset and the run ends",
             dependencies=[requires(Role.OPERATOR, action="jobs.stop")])
def stop_run(session: SessionDep, settings: SettingsDep, principal: PrincipalDep,
             job_id: str, by: RecordedBy) -> dict[str, Any]:
    with resource_errors():
        if principal.machines is not None:
            job = service.get_job(session=session, job_id=job_id)
            check_machines(principal, [t.machine_id for t in job.targets])
        n = runs.request_stop(session=session, settings=settings, job_id=job_id,
                                   stopped_by=by)
    return {"id": job_id, "stopping": n}


@router.get("/api/runs", summary="Drip-feed runs, newest first: the run history",
            dependencies=[requires(Role.VIEWER)])
def list_runs(
        session: SessionDep,
        machine: Annotated[str | None, Query(description="Only this machine's runs")] = None,
        program: Annotated[str | None, Query(description="Only runs of this program name")]
        = None,
        state: RunState | None = None,
        since: Annotated[datetime | None, Query(description="Made at or after this time")]
        = None,
        until: Annotated[datetime | None, Query(description="Made before this time")] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> list[dict[str, Any]]:
    found = run_views.list_runs(session=session, machine_id=machine, program=program, state=state,
                           since=since, until=until, limit=limit)
    with resource_errors():  # a mistyped machine: 10003, not an empty list
        registry.check_machine_filter(session=session, machine_id=machine or None,
                                      held_by=Run.machine_id, found=found)
    return [run_views.view(r) for r in found]


@router.get("/api/runs/{run_id}", summary="One drip-feed run",
            dependencies=[requires(Role.VIEWER)])
def get_run(session: SessionDep,
            run_id: Annotated[int, Path(ge=1, le=2**63 - 1)]) -> dict[str, Any]:  # a BIGINT
    run = session.get(Run, run_id)
    if run is None:
        raise CodedHTTPError(404, ErrorCode.PATH_NOT_FOUND, f"no run {run_id}")
    return run_views.view(run)
