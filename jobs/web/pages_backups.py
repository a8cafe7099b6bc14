"""The backups pages: the list by date, machine and state; one backup as a tree (download,
verify, restore a folder); two backups, or a backup and the machine now, compared."""

from __future__ import annotations

import difflib
import re
import zipfile
from datetime import datetime, timedelta
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse, Response
from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from jobs import rollout
from jobs.backup import manifests, store
from jobs.backup.restore import restore_targets, separators_of, split_path
from jobs.backup_models import Backup, BackupFile, BackupMachine, BackupStatus, MachineBackupStatus
from jobs.errors import ContractError, ErrorCode, resource_status
from jobs.fleet import registry
from jobs.job_options import JobOptions
from jobs.library.service import DIFF_MAX_BYTES
from jobs.models import JobKind
from jobs.run.slot import opened
from jobs.settings import Settings
from jobs.web.deps import (
    PageRoute,
    SessionDep,
    SettingsDep,
    Viewer,
    ViewerDep,
    acting,
    audit,
    render,
    said,
    told,
)
from jobs.web.principal import Role
from jobs.web.refusals import audited_as

router = APIRouter(route_class=PageRoute)

Operator = Annotated[Viewer, Depends(acting(Role.OPERATOR))]


def _day(text: str) -> datetime | None:
    try:
        return datetime.fromisoformat(text).astimezone() if text else None
    except ValueError:
        return None


@router.get("/backups", response_class=HTMLResponse)
def backups_page(request: Request, session: SessionDep, who: ViewerDep, day: str = "",
                 machine: str = "", state: str = "") -> Response:
    query = select(Backup).options(selectinload(Backup.machines))
    since = _day(day)
    if since is not None:  # the whole day, in the server's time zone
        query = query.where(Backup.created_at >= since,
                            Backup.created_at < since + timedelta(days=1))
    if machine:
        query = query.where(select(BackupMachine.id).where(
            BackupMachine.backup_id == Backup.id, BackupMachine.machine_id == machine).exists())
    if state in set(BackupStatus):
        query = query.where(Backup.status == BackupStatus(state))
    found = session.scalars(query.order_by(Backup.created_at.desc()).limit(500)).all()
    # a mistyped id is said, with the one it was likely typed for
    registry.check_machine_filter(session=session, machine_id=machine or None,
                                  held_by=BackupMachine.machine_id, found=found)
    return render(request, who, "backups.html", backups=[_listed(b) for b in found],
                  states=[s.value for s in BackupStatus],
                  chosen={"day": day, "machine": machine, "state": state})


def _listed(backup: Backup) -> dict[str, Any]:
    """A backup as the list shows it: a partial one with the machines not backed up whole,
    the first FAILED_NAMED named (`failed`) and the rest counted (`failedMore`)."""
    view = manifests.view(backup)
    failed = [m for m in view["machines"] if m["status"] is not MachineBackupStatus.OK] \
        if backup.status is BackupStatus.PARTIAL else []
    return {**view, "failed": failed[:FAILED_NAMED],
            "failedMore": max(len(failed) - FAILED_NAMED, 0)}


FAILED_NAMED = 3  # machines a partial backup's row names; a row of 50 would fill the page


def _tree(session: Session, files: list[BackupFile]) -> dict[str, Any]:
    """Machine → folder → files: the manifest as nested folders, split by each machine's
    own separator (a `\\` in a name on a machine of `/` folders is a letter)."""
    tree: dict[str, Any] = {}
    separators = separators_of(session=session, machine_ids={f.machine_id for f in files})
    for f in files:
        separator = separators[f.machine_id]
        folder, name = split_path(f.path, separator)
        node = tree.setdefault(f.machine_id, {"folders": {}, "files": []})
        parts = f"[^{re.escape(separator)}]+" if separator else r"[^/\\]+"  # gone: either
        for part in re.finditer(parts, folder):  # each folder with its path as written
            node = node["folders"].setdefault(part.group(), {
                "folders": {}, "files": [], "path": folder[:part.end()]})
        node["files"].append({"name": name, "size": f.size, "mtime": f.mtime,
                              "sha256": f.sha256, "path": f.path})
    return tree


@router.get("/backups/diff", response_class=HTMLResponse)
def backups_diff(request: Request, session: SessionDep, settings: SettingsDep,
                 who: ViewerDep, first: str, second: str = "", machine: str = "") -> Response:
    """Two backups compared; with `second` empty, `first` and `machine` as it is now."""
    old = manifests.get(session=session, backup_id=first)
    if second:
        new = manifests.get(session=session, backup_id=second)
        changes = manifests.diff(first=old, second=new, machine_id=machine or None)
        lines = {(m, p): _line_diff(_member(settings, old, m, p), _member(settings, new, m, p),
                                    first, second)
                 for m, c in changes.items() for p in c["changed"]}
        title = f"{old.name} → {new.name}"
    else:
        if not machine:
            raise ContractError(ErrorCode.BAD_PARAMETER, "name the machine to compare with")
        changes, lines = _against_machine(session, settings, old, machine)
        title = f"{old.name} → machine {machine} now"
    return render(request, who, "backup_diff.html", changes=changes, lines=lines, title=title,
                  first=first, second=second)


def _member(settings: Settings, backup: Backup, machine_id: str, path: str) -> bytes:
    found = next(f for f in backup.files if f.machine_id == machine_id and f.path == path)
    if found.size > DIFF_MAX_BYTES:
        return b""
    with zipfile.ZipFile(store.backup_dir(settings) / backup.name) as archive:
        return archive.read(found.archive_path)


def _line_diff(before: bytes, after: bytes, old: str, new: str) -> str:
    text = difflib.unified_diff(before.decode("latin-1").splitlines(keepends=True),
                                after.decode("latin-1").splitlines(keepends=True),
                                fromfile=old, tofile=new)
    return "".join(line if line.endswith("\n") else line + "\n" for line in text)


def _against_machine(session: Session, settings: Settings, backup: Backup, machine_id: str
                     ) -> tuple[dict[str, dict[str, Any]], dict[tuple[str, str], str]]:
    """The backup's files of a machine read from the machine now: changed, gone, or not
    readable (too large, refused) with why. A machine that cannot be read at all (offline,
    busy) is refused whole: its files are not gone."""
    mine = [f for f in backup.files if f.machine_id == machine_id]
    changed, removed, unread, lines = [], [], [], {}
    with opened(session, settings, machine_id, reading=True) as files:
        for f in mine:
            folder, name = split_path(f.path, files.row.separator)
            try:
                now = files.read_bytes(files.listed_ref(name, folder or None, None),
                                       max_bytes=DIFF_MAX_BYTES)
            except ContractError as exc:
                if exc.code is ErrorCode.PATH_NOT_FOUND:
                    removed.append(f.path)
                elif exc.code in _FILE_REFUSALS:
                    unread.append(f"{f.path}: {said(exc)}")
                else:
                    raise
                continue
            then = _member(settings, backup, machine_id, f.path)
            if now != then:
                changed.append(f.path)
                lines[(machine_id, f.path)] = _line_diff(then, now, backup.name, "now")
    held = {m.machine_id: m.status.value for m in backup.machines}.get(machine_id,
                                                                        manifests.ABSENT)
    incomplete = {} if held == MachineBackupStatus.OK.value else {backup.id: held}
    return {machine_id: {"added": [], "removed": removed, "changed": changed,
                         "unread": unread, "incomplete": incomplete}}, lines


# What one file's read may meet while its machine answers: the others are still compared.
_FILE_REFUSALS = {ErrorCode.FILE_TOO_LARGE, ErrorCode.PERMISSION_DENIED, ErrorCode.BAD_PARAMETER,
                  ErrorCode.PATH_OUTSIDE_ROOT}


@router.get("/backups/{backup_id}", response_class=HTMLResponse)
def backup_page(request: Request, session: SessionDep, who: ViewerDep,
                backup_id: str) -> Response:
    backup = manifests.get(session=session, backup_id=backup_id)
    others = session.scalars(select(Backup).where(Backup.id != backup_id)
                             .order_by(Backup.created_at.desc()).limit(50)).all()
    return render(request, who, "backup.html", backup=manifests.view(backup, session=session),
                  tree=_tree(session, list(backup.files)), others=others,
                  message=request.query_params.get("message"))


@router.get("/backups/{backup_id}/download")
def backup_download(session: SessionDep, settings: SettingsDep, who: ViewerDep,
                    backup_id: str) -> Response:
    backup = manifests.get(session=session, backup_id=backup_id)
    return FileResponse(store.backup_dir(settings) / backup.name, media_type="application/zip",
                        filename=backup.name)


@router.post("/backups/{backup_id}/verify")
@audited_as("verify backup")
def backup_verify(request: Request, session: SessionDep, settings: SettingsDep,
                  who: Operator, backup_id: str) -> Response:
    backup = manifests.get(session=session, backup_id=backup_id)
    problems = manifests.verify(settings=settings, backup=backup)
    message = "Sound: every CRC and SHA-256 matches." if not problems else \
        f"{len(problems)} problem(s): " + "; ".join(problems[:5])
    audit(request, session, who, action="verify backup", target=backup_id)
    return told(f"/backups/{backup_id}", message)


@router.post("/backups/{backup_id}/restore")
@audited_as("restore backup")
def backup_restore(request: Request, session: SessionDep, settings: SettingsDep,
                   who: Operator, backup_id: str, machine: Annotated[str, Form()],
                   path: Annotated[str, Form()] = "",
                   replace: Annotated[str, Form()] = "") -> Response:
    who.may_change([machine])
    backup = manifests.get(session=session, backup_id=backup_id)
    unknown = rollout.unknown(session=session, selector=rollout.Selector(ids=[machine]))
    try:
        if unknown:
            raise rollout.refuse_unknown(unknown)
        targets = restore_targets(session=session, settings=settings, backup=backup,
                                  machine_id=machine, path=path or None)
    except ContractError as exc:
        # as the API answers it: a machine nobody registered refuses the whole request
        # (422), a backup that holds nothing of it is missing (404), a damaged one 409
        audit(request, session, who, action="restore backup", target=backup_id,
              status=422 if unknown else resource_status(exc),
              detail={"machine": machine, "path": path})
        return told(f"/backups/{backup_id}", f"Not restored: {exc.status_msg}")
    job = rollout.submit(
        session=session, settings=settings, kind=JobKind.RESTORE, targets=targets,
        options=JobOptions(replace=replace == "on", make_dirs=True, restore_from=backup.id),
        created_by=who.principal.name,
        recorded=lambda job: audit(request, session, who, action="restore backup",
                                   target=backup_id, detail={"machine": machine, "path": path,
                                                             "job": job.id}))
    return RedirectResponse(f"/jobs/{job.id}", status_code=303)
