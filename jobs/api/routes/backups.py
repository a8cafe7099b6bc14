"""Stored backups: list, download, manifest, verify, diff, restore."""

from __future__ import annotations

from datetime import datetime
from functools import partial
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict
from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from jobs import job_views, rollout
from jobs.api import waiting
from jobs.api.deps import PrincipalDep, SessionDep, SettingsDep, check_machines, requires
from jobs.api.errors import CodedHTTPError, refused_whole, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.backup import manifests, store
from jobs.backup.restore import restore_targets
from jobs.backup_models import Backup, BackupMachine, BackupStatus
from jobs.errors import ErrorCode
from jobs.fleet import registry
from jobs.job_options import JobOptions
from jobs.models import JobKind

router = APIRouter(prefix="/api/backups", tags=["backups"], route_class=CheckedRoute)


def _get(session: Any, backup_id: str) -> Backup:
    with resource_errors():
        return manifests.get(session=session, backup_id=backup_id)


@router.get("", summary="Stored backups, newest first",
            dependencies=[requires(Role.VIEWER)])
async def list_backups(
        session: SessionDep, settings: SettingsDep,
        job: Annotated[str | None, Query(
            description="Only the backup this job made (none while it is being assembled)",
            max_length=32)] = None,
        since: Annotated[datetime | None, Query(description="Made at or after this time")]
        = None,
        until: Annotated[datetime | None, Query(description="Made before this time")] = None,
        machine: Annotated[str | None, Query(description="Only backups that hold this machine",
                                             max_length=64)] = None,
        state: Annotated[BackupStatus | None, Query(
            description="complete, partial or failed")] = None,
        limit: Annotated[int, Query(ge=1, le=5000)] = 500,
        wait_s: Annotated[float, Query(ge=0, le=waiting.WAIT_MAX_S, description=(
            "With `job`: answer once its backup is registered or none will be (the job "
            "ended and its ZIP could not be written), or after this many seconds"))]
        = 0,
) -> list[dict[str, Any]]:
    if wait_s and job is None:
        raise CodedHTTPError(400, ErrorCode.BAD_PARAMETER, "wait_s waits for a job's backup: "
                                                           "give the job too")
    if wait_s and job is not None:  # answered the moment the ZIP is registered, or is not to be
        await waiting.until(settings, job, wait_s, partial(waiting.backup_made, settings=settings))
    return await run_in_threadpool(_listed, session, job, since, until, machine, state, limit)


def _listed(session: Session, job: str | None, since: datetime | None, until: datetime | None,
            machine: str | None, state: BackupStatus | None, limit: int) -> list[dict[str, Any]]:
    query = select(Backup).options(selectinload(Backup.machines))
    if job is not None:
        query = query.where(Backup.job_id == job)
    if since is not None:
        query = query.where(Backup.created_at >= since)
    if until is not None:
        query = query.where(Backup.created_at < until)
    if machine is not None:
        query = query.where(select(BackupMachine.id).where(
            BackupMachine.backup_id == Backup.id, BackupMachine.machine_id == machine).exists())
    if state is not None:
        query = query.where(Backup.status == state)
    found = session.scalars(query.order_by(Backup.created_at.desc()).limit(limit)).all()
    with resource_errors():  # a mistyped machine: 10003, not an empty list
        registry.check_machine_filter(session=session, machine_id=machine,
                                      held_by=BackupMachine.machine_id, found=found)
    return [manifests.view(b) for b in found]


@router.get("/{backup_id}", summary="Download the backup ZIP",
            response_class=FileResponse, responses={200: {"content": {"application/zip": {}}}},
            dependencies=[requires(Role.VIEWER)])
def download(session: SessionDep, settings: SettingsDep, backup_id: str) -> FileResponse:
    backup = _get(session, backup_id)
    path = store.backup_dir(settings) / backup.name
    if not path.is_file():
        raise CodedHTTPError(404, ErrorCode.PATH_NOT_FOUND, f"{backup.name} is missing")
    return FileResponse(path, media_type="application/zip", filename=backup.name)


@router.get("/{backup_id}/manifest", summary="Every file of the backup, with its SHA-256",
            dependencies=[requires(Role.VIEWER)])
def manifest(session: SessionDep, backup_id: str) -> dict[str, Any]:
    return manifests.manifest(session=session, backup=_get(session, backup_id))


@router.post("/{backup_id}/verify", summary="Re-read the ZIP: every CRC and SHA-256",
             dependencies=[requires(Role.OPERATOR, action="backups.verify")])
def verify(session: SessionDep, settings: SettingsDep, backup_id: str) -> dict[str, Any]:
    problems = manifests.verify(settings=settings, backup=_get(session, backup_id))
    return {"id": backup_id, "ok": not problems, "problems": problems}


@router.get("/{first_id}/diff/{second_id}", summary="Files added, removed, changed per machine",
            dependencies=[requires(Role.VIEWER)])
def diff(session: SessionDep, first_id: str, second_id: str,
         machine: str | None = None) -> dict[str, Any]:
    return manifests.diff(first=_get(session, first_id), second=_get(session, second_id),
                             machine_id=machine)


class RestoreRequest(BaseModel):
    """What to put back where."""

    model_config = ConfigDict(extra="forbid")

    machine: str  # whose files, as backed up
    path: str | None = None  # a file or folder of it, below its root (O1234) or whole; default: all
    to: str | None = None  # another machine to restore onto; default: the same one
    replace: bool = False  # replace files that are there (the replaced ones are kept)


@router.post("/{backup_id}/restore", status_code=202,
             summary="Send files of a backup back to a machine, as a restore job",
             dependencies=[requires(Role.OPERATOR, action="backups.restore")])
def restore(session: SessionDep, settings: SettingsDep, principal: PrincipalDep,
            backup_id: str, request: RestoreRequest) -> dict[str, Any]:
    destination = request.to or request.machine
    check_machines(principal, [destination])
    backup = _get(session, backup_id)
    # refused whole, as the job API refuses an unknown id (its targets would all fail)
    if found := rollout.unknown(session=session, selector=rollout.Selector(ids=[destination])):
        raise refused_whole(rollout.refuse_unknown(found))
    with resource_errors():  # a missing or damaged ZIP refuses the whole restore before any send
        targets = restore_targets(session=session, settings=settings, backup=backup,
                                  machine_id=request.machine, path=request.path, to=request.to)
    job = rollout.submit(session=session, settings=settings, kind=JobKind.RESTORE, targets=targets,
                         options=JobOptions(replace=request.replace, make_dirs=True,
                                            restore_from=backup.id),
                         created_by=f"restore of backup {backup_id}")
    return job_views.view(session=session, job=job)
