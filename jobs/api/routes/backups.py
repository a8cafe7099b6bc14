"""Stored backups: list, download, manifest, verify, diff, restore."""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict
from sqlalchemy import select
from sqlalchemy.orm import selectinload

from jobs import rollout, service
from jobs.api.deps import PrincipalDep, SessionDep, SettingsDep, check_machines, requires
from jobs.api.errors import CodedHTTPError, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.backup import store
from jobs.backup.restore import restore_files
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.job_options import JobOptions
from jobs.models import Backup, BackupMachine, BackupStatus, JobKind

router = APIRouter(prefix="/api/backups", tags=["backups"], route_class=CheckedRoute)


def _get(session: Any, backup_id: str) -> Backup:
    with resource_errors():
        return store.get(session=session, backup_id=backup_id)


@router.get("", summary="Stored backups, newest first",
            dependencies=[requires(Role.VIEWER)])
def list_backups(
        session: SessionDep,
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
) -> list[dict[str, Any]]:
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
    return [store.view(b) for b in session.scalars(
        query.order_by(Backup.created_at.desc()).limit(limit)).all()]


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
    return store.manifest(_get(session, backup_id))


@router.post("/{backup_id}/verify", summary="Re-read the ZIP: every CRC and SHA-256",
             dependencies=[requires(Role.OPERATOR, action="backups.verify")])
def verify(session: SessionDep, settings: SettingsDep, backup_id: str) -> dict[str, Any]:
    problems = store.verify(settings=settings, backup=_get(session, backup_id))
    return {"id": backup_id, "ok": not problems, "problems": problems}


@router.get("/{first_id}/diff/{second_id}", summary="Files added, removed, changed per machine",
            dependencies=[requires(Role.VIEWER)])
def diff(session: SessionDep, first_id: str, second_id: str,
         machine: str | None = None) -> dict[str, Any]:
    return store.diff(first=_get(session, first_id), second=_get(session, second_id),
                             machine_id=machine)


class RestoreRequest(BaseModel):
    """What to put back where."""

    model_config = ConfigDict(extra="forbid")

    machine: str  # whose files, as backed up
    path: str | None = None  # a file or folder on that machine; default: all of it
    to: str | None = None  # another machine to restore onto; default: the same one
    replace: bool = False  # replace files that are there (the replaced ones are kept)


@router.post("/{backup_id}/restore", status_code=202,
             summary="Send files of a backup back to a machine, as a restore job",
             dependencies=[requires(Role.OPERATOR, action="backups.restore")])
def restore(session: SessionDep, settings: SettingsDep, principal: PrincipalDep,
            backup_id: str, request: RestoreRequest) -> dict[str, Any]:
    check_machines(principal, [request.to or request.machine])
    backup = _get(session, backup_id)
    place = _place_on(session, request.machine)
    targets: list[service.TargetIn] = []
    with resource_errors():  # a missing or damaged ZIP refuses the whole restore before any send
        files = restore_files(settings=settings, backup=backup,
                              machine_id=request.machine, path=request.path)
    for f in files:  # the runners read each file from the ZIP as they send it
        folder, name = _split(f.path)
        dir_at_cnc, sub_dir = place(folder)
        targets.append(service.TargetIn(machineID=request.to or request.machine, fileName=name,
                                        dirAtCNC=dir_at_cnc, subDir=sub_dir,
                                        archivePath=f.archive_path))
    job = rollout.submit(session=session, settings=settings, kind=JobKind.RESTORE, targets=targets,
                         options=JobOptions(replace=request.replace, make_dirs=True,
                                            restore_from=backup.id),
                         created_by=f"restore of backup {backup_id}")
    return service.view(session=session, job=job)


def _place_on(session: Any, machine_id: str) -> Callable[[str], tuple[str | None, str | None]]:
    """How a backed-up folder is named to the machine a restore sends to.

    A folder below the backed-up machine's default root goes as a `subDir` (no folder at
    all for a file in the root), so that it lands below the default root of whichever
    machine receives it, even a model that takes no target folder (Fanuc 18i) or writes
    its root another way; a folder of another root is sent as it was written.
    """
    try:
        spec = registry.get(session=session, machine_id=machine_id)
        paths = registry.paths_of(spec)
    except ContractError:  # the backed-up machine is gone: the folders as written
        return lambda folder: (folder or None, None)

    def place(folder: str) -> tuple[str | None, str | None]:
        try:
            found = paths.parse(folder) if folder else None
        except ContractError:
            return folder, None
        if found is None or found.root != paths.default:
            return folder or None, None
        return None, "/".join(found.parts) or None

    return place


def _split(machine_path: str) -> tuple[str, str]:
    """A machine path into its folder (as the model writes it) and file name."""
    cut = max(machine_path.rfind("/"), machine_path.rfind("\\"))
    return machine_path[:cut + 1], machine_path[cut + 1:]
