"""The job API: submit batch work that returns at once, follow it, retry, cancel."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query
from fastapi import Request as HttpRequest
from fastapi.concurrency import run_in_threadpool
from pydantic import Field

from jobs import job_views, rollout, service
from jobs.api import library_send, waiting
from jobs.api.deps import (
    PrincipalDep,
    RecordedBy,
    SessionDep,
    SettingsDep,
    check_machines,
    note_target,
    recorded_as,
    requires,
)
from jobs.api.errors import RoleRefused, refused_whole, resource_errors
from jobs.api.routes import runs
from jobs.api.routes.cnc import FileContent, content_bytes
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Principal, Role, refusal, role_for_job
from jobs.dnc import runs as dnc_runs
from jobs.dnc.modal import MachineKind
from jobs.dnc.starting import RestartAsked
from jobs.errors import ContractError
from jobs.fleet import registry
from jobs.job_options import JobOptions, RolloutOptions
from jobs.models import JobKind, JobState, Target, TargetState
from jobs.run import job_ends, settle

router = APIRouter(prefix="/api/jobs", tags=["jobs"], route_class=CheckedRoute)

_RUN_ONLY = ("program", "from_block", "from_line", "from_tool", "machine_kind", "queue")


class JobRequest(RolloutOptions):
    """A batch job: what to do, to which machines, how carefully (the rollout options)."""

    kind: JobKind
    content: str | None = None
    encoding: str | None = None
    base64: str | None = None
    targets: list[dict[str, Any]] | None = Field(
        default=None, description="Targets as the contract writes them; or use `machines`")
    machines: rollout.Selector | None = None
    fileName: str | None = None
    dirAtCNC: str | None = None
    subDir: str | None = None
    includeSubDir: bool | None = None
    dry_run: bool = False
    allow_unknown: bool = Field(default=False, description=(
        "Queue the job even when `machines` names ids or tags no machine has; without it, "
        "such a request is refused whole (HTTP 422) naming them"))
    created_by: str = "api"
    program: str | None = Field(default=None, description=(
        "dnc_run: the stored program to run, the id `POST /api/programs` answered"))
    from_block: str | None = Field(default=None, description=(
        "dnc_run: restart from this block number (`N1234`)"))
    from_line: int | None = Field(default=None, ge=1, description=(
        "dnc_run: restart from this line of the program's file"))
    from_tool: str | None = Field(default=None, description=(
        "dnc_run: restart at the change to this tool (`T7`): its first change, or with "
        "`from_line` its last change at or before that line"))
    machine_kind: MachineKind | None = Field(default=None, description=(
        "dnc_run restart: read the program as a mill's or a lathe's (default: from its codes)"))
    queue: bool = Field(default=False, description=(
        "dnc_run: queue the run behind one its machine has queued or running, to start when "
        "that one ends, whatever the machine's `max_concurrent` (its DNC link feeds one "
        "program at a time); without it, such a request is refused (HTTP 409, 20007) naming it"))
    library: str | None = Field(default=None, description=(
        "send: the library program to send (`VIPROS/0010`) instead of `content`"))
    library_version: int | None = Field(default=None, ge=1, description=(
        "send with `library`: this version, whatever its state (default: the current "
        "approved one)"))

    def options(self) -> JobOptions:
        """The rollout options."""
        return JobOptions(
            **self.model_dump(include=set(RolloutOptions.model_fields)))


@router.post("", status_code=202, summary="Submit a send, delete, backup or drip-feed run job",
             dependencies=[requires(Role.OPERATOR, action="jobs.create", by_route=True,
                                   least_what="a job of any kind")])
def submit_job(http: HttpRequest, session: SessionDep, settings: SettingsDep,
               principal: PrincipalDep, request: JobRequest) -> Any:
    needed = role_for_job(request.kind)
    if not principal.may(needed):
        raise RoleRefused(refusal(principal, needed, f"a {request.kind.value} job"))
    if request.kind is JobKind.DNC_RUN:
        if principal.machines is not None:
            check_machines(principal, runs.machine_ids(session, request.machines,
                                                       request.targets))
        return _noted(http, runs.submit_run(
            session=session, settings=settings, program=request.program,
            library=request.library, library_version=request.library_version,
            file_name=request.fileName, machines=request.machines, targets=request.targets,
            restart=RestartAsked(from_block=request.from_block, from_line=request.from_line,
                                 from_tool=request.from_tool,
                                 machine_kind=request.machine_kind),
            dry_run=request.dry_run, queue=request.queue,
            created_by=recorded_as(principal, request.created_by)))
    if request.kind is JobKind.RESTORE:
        raise HTTPException(422, detail="a restore job starts from a backup (POST "
                                        "/api/backups/{id}/restore) or a replace job (POST "
                                        "/api/jobs/{id}/restore-replaced)")
    if request.kind is JobKind.REQUEST:
        raise HTTPException(422, detail="a request job is recorded when a machine's operator "
                                        "sends one from the control (GET /api/jobs?kind=request "
                                        "lists them); it is not submitted")
    if given := [name for name in _RUN_ONLY if getattr(request, name) not in (None, False)]:
        # not ignored: a send told "queue": true or a from_line went as if it had not been
        raise HTTPException(422, detail=f"{', '.join(given)}: for a dnc_run job only, not a "
                                        f"{request.kind.value} job")
    found: rollout.Unknown | None = None
    if request.targets is not None:
        if request.machines is not None or request.fileName or request.dirAtCNC \
                or request.subDir or request.includeSubDir is not None:
            raise HTTPException(422, detail="give targets, or machines with fileName, dirAtCNC, "
                                            "subDir and includeSubDir; not both")
        targets = [service.TargetIn.parse(t) for t in request.targets]
    elif request.machines is not None:
        found = rollout.unknown(session=session, selector=request.machines)
        if found and not (request.allow_unknown or request.dry_run):
            raise refused_whole(rollout.refuse_unknown(found))
        try:
            targets = rollout.select_targets(session=session, selector=request.machines,
                                             file_name=request.fileName,
                                             dir_at_cnc=request.dirAtCNC, sub_dir=request.subDir)
        except ContractError as exc:
            if found:  # nothing is left once the unknown ones are set aside: name them
                raise refused_whole(rollout.refuse_unknown(found)) from None
            raise refused_whole(exc) from None  # a selection that picks no machine
        for t in targets:
            t.includeSubDir = request.includeSubDir
    else:
        raise HTTPException(422, detail="give targets or machines")
    check_machines(principal, [t.machineID for t in targets if not t.problem])
    options = request.options()
    data: bytes | None = None
    sent = None
    if request.library is not None:
        sent = library_send.version(session=session, settings=settings, request=request)
        data = library_send.content(settings=settings, sent=sent)
        explicit = True
        for t in targets:
            t.fileName = t.fileName or sent.program.name
    elif request.kind is JobKind.SEND:
        file = FileContent(content=request.content, encoding=request.encoding,
                           base64=request.base64)
        explicit = request.content is None or request.encoding is not None
        # Bad Base64, an unknown encoding: 400, as errors.install answers a bad parameter.
        data = content_bytes(file, "utf-8") if explicit else request.content.encode()  # type: ignore[union-attr]
    if request.dry_run:
        return {"dryRun": True, "targets": rollout.dry_run(
            session=session, settings=settings, kind=request.kind, targets=targets,
            options=options, data=data),
            "unknown": {"ids": found.ids, "tags": found.tags,
                        "message": found.message()} if found else None}
    payload_id, per_target = None, None
    if request.kind is JobKind.SEND:
        payload_id, per_target = rollout.payloads(
            session=session, targets=targets, content=request.content,
            data=data if explicit else None)
    job = rollout.submit(session=session, settings=settings, kind=request.kind,
                         targets=targets, options=options, payload_id=payload_id,
                         target_payloads=per_target,
                         created_by=recorded_as(principal, request.created_by),
                         recorded=library_send.recorder(sent))
    note_target(http, job.id, kind=request.kind.value)
    return library_send.view(session=session, job=job)


def _noted(http: HttpRequest, body: dict[str, Any]) -> dict[str, Any]:
    """The answer, its job id noted as the audit trail's target."""
    if body.get("id"):
        note_target(http, str(body["id"]), kind=JobKind.DNC_RUN.value)
    return body


def check_job_machines(principal: Principal, job: Any) -> None:
    """403 unless every machine of the job is one of the principal's."""
    if principal.machines is not None:
        check_machines(principal, [t.machine_id for t in job.targets])


@router.get("", summary="List jobs",
            dependencies=[requires(Role.VIEWER)])
def list_jobs(session: SessionDep, state: JobState | None = None, kind: JobKind | None = None,
              machine: str | None = None, since: datetime | None = None,
              until: datetime | None = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> list[dict[str, Any]]:
    found = service.list_jobs(session=session, state=state, kind=kind, machine_id=machine,
                              since=since, until=until, limit=limit)
    with resource_errors():  # a mistyped machine: 10003, not an empty list
        registry.check_machine_filter(session=session, machine_id=machine or None,
                                      held_by=Target.machine_id, found=found)
    return [library_send.view(session=session, job=j) for j in found]


@router.get("/{job_id}", summary="A job's progress and one page of its targets, in order",
            dependencies=[requires(Role.VIEWER)])
async def get_job(
        session: SessionDep, settings: SettingsDep, job_id: str,
        limit: Annotated[int, Query(ge=0, le=job_views.TARGET_PAGE_MAX, description=(
            "Targets in the page (0: the summary only)"))] = job_views.TARGET_PAGE_DEFAULT,
        after: Annotated[int | None, Query(ge=-1, le=2**63 - 1, description=(  # a BIGINT
            "Targets after this position: the previous page's `nextAfter`"))] = None,
        state: Annotated[TargetState | None, Query(description="Only targets in this state")]
        = None,
        machine: Annotated[str | None, Query(description="Only this machine's targets")] = None,
        wait_s: Annotated[float, Query(ge=0, le=waiting.WAIT_MAX_S, description=(
            "Answer once no target is left to run, or after this many seconds"))] = 0,
) -> dict[str, Any]:
    if wait_s:  # the answer comes the moment the job ends (an unknown one's 404 at once)
        await waiting.until(settings, job_id, wait_s, settle.is_finished)

    def view() -> dict[str, Any]:
        with resource_errors():
            job = service.get_job(session=session, job_id=job_id)
        page = job_views.TargetPage(limit=limit, after=after, state=state, machine_id=machine)
        if job.kind is JobKind.DNC_RUN:
            shown = runs.job_view(session=session, job_id=job.id, page=page)
        else:
            shown = library_send.view(session=session, job=job, page=page)
        with resource_errors():  # a mistyped machine: 10003, not an empty page
            registry.check_machine_filter(session=session, machine_id=machine or None,
                                          held_by=Target.machine_id, found=shown["targets"])
        return shown

    return await run_in_threadpool(view)


@router.post("/{job_id}/retry", summary="Run the failed targets again",
             dependencies=[requires(Role.PROGRAMMER, action="jobs.retry")])
def retry_job(session: SessionDep, settings: SettingsDep, principal: PrincipalDep,
              job_id: str) -> dict[str, Any]:
    with resource_errors():
        check_job_machines(principal, service.get_job(session=session, job_id=job_id))
        n = service.retry_failed(session=session, job_id=job_id)
    session.commit()
    service.dispatch(settings=settings, job_id=job_id)
    return {"id": job_id, "retried": n}


@router.post("/{job_id}/cancel", summary="Cancel the targets not started yet",
             dependencies=[requires(Role.OPERATOR, action="jobs.cancel", by_route=True)])
def cancel_job(session: SessionDep, settings: SettingsDep, principal: PrincipalDep,
               job_id: str, by: RecordedBy) -> dict[str, Any]:
    with resource_errors():
        job = service.get_job(session=session, job_id=job_id)
        needed = role_for_job(job.kind)
        if not principal.may(needed):  # the kind's role, not the route's least one
            raise RoleRefused(refusal(principal, needed, f"cancelling a {job.kind.value} job"))
        check_job_machines(principal, job)
        if job.kind is JobKind.DNC_RUN:  # a run that is not stopped would go on cutting
            n = dnc_runs.request_stop(session=session, settings=settings, job_id=job_id,
                                        stopped_by=by)
        else:
            n = service.cancel(session=session, job_id=job_id)
    session.commit()
    job_ends.announce(settings, job_id)  # a request waiting for the job may answer now
    return {"id": job_id, "cancelled": n}


@router.post("/{job_id}/restore-replaced", status_code=202,
             summary="Put back every file a replace job overwrote",
             dependencies=[requires(Role.PROGRAMMER, action="jobs.restore_replaced")])
def restore_replaced(session: SessionDep, settings: SettingsDep, principal: PrincipalDep,
                     job_id: str) -> dict[str, Any]:
    with resource_errors():
        job = service.get_job(session=session, job_id=job_id)
    check_job_machines(principal, job)
    if not any(t.replaced_payload_id for t in job.targets):
        raise HTTPException(409, detail=f"job {job_id} replaced no file")
    restore = rollout.restore_replaced(session=session, settings=settings, job=job,
                                       created_by=f"restore of {job_id}")
    return job_views.view(session=session, job=restore)
