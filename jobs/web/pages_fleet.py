"""The fleet page and a machine's page: its files (moved as the role allows), jobs,
backups, runs, and a check."""

from __future__ import annotations

import io
import logging
from collections.abc import Callable
from typing import Annotated, Any
from urllib.parse import quote, urlencode

from fastapi import APIRouter, Depends, File, Form, Request, UploadFile
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from jobs import job_views, service
from jobs.backup_models import Backup, BackupMachine
from jobs.dnc import run_views
from jobs.errors import ContractError, library_status
from jobs.fleet import checks, door, registry
from jobs.fleet.paths import Place
from jobs.fleet.rules import FANUC_HEAD_BYTES, MachineFiles
from jobs.models import Job, Run, RunState, Target, utcnow
from jobs.run.checking import check_now
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
)
from jobs.web.principal import Role
from jobs.web.refusals import audited_as

router = APIRouter(route_class=PageRoute)
log = logging.getLogger(__name__)

FLEET_REFRESH_S = 30  # the fleet page reloads itself this often (a wall display stays fresh)
DOWNLOAD_MAX_BYTES = 64 * 1024 * 1024  # a program read whole for the browser
PAGE_WAIT_S = 5.0  # a page waits this long for a busy machine's listing, then says it is busy
Operator = Annotated[Viewer, Depends(acting(Role.OPERATOR))]
Reader = Annotated[Viewer, Depends(acting(Role.VIEWER))]


def _last_by_machine(session: Session) -> tuple[dict[str, Any], dict[str, Any]]:
    """Each machine's last backup time and last job time."""
    backups = dict(session.execute(
        select(BackupMachine.machine_id, func.max(Backup.created_at))
        .join(Backup, Backup.id == BackupMachine.backup_id)
        .group_by(BackupMachine.machine_id)).all())
    jobs = dict(session.execute(
        select(Target.machine_id, func.max(Job.created_at))
        .join(Job, Job.id == Target.job_id).group_by(Target.machine_id)).all())
    return backups, jobs


def _state(check: dict[str, Any] | None, run: Run | None, settings: Settings) -> str:
    if run is not None:
        return "running"
    return checks.state(check, now=utcnow(), max_age_s=settings.check_max_age_s)


@router.get("/", response_class=HTMLResponse)
def fleet(request: Request, session: SessionDep, settings: SettingsDep, who: ViewerDep,
          tag: str = "", model: str = "", state: str = "", q: str = "",
          view: str = "grid") -> Response:
    specs = registry.list_all(session=session)
    last_checks = checks.latest(session)
    running = {r.machine_id: r for r in session.scalars(
        select(Run).where(Run.state == RunState.RUNNING))}
    last_backup, last_job = _last_by_machine(session)
    rows = []
    for spec in specs:
        check = last_checks.get(spec.id)
        row = {"spec": spec, "check": check, "run": running.get(spec.id),
               "state": _state(check, running.get(spec.id), settings),
               "last_backup": last_backup.get(spec.id), "last_job": last_job.get(spec.id)}
        text = f"{spec.id} {spec.name} {spec.model} {spec.transport} {' '.join(spec.tags)}"
        if (tag and tag not in spec.tags) or (model and spec.model != model) or \
                (state and row["state"] != state) or (q and q.lower() not in text.lower()):
            continue
        rows.append(row)
    return render(request, who, "fleet.html", rows=rows, total=len(specs),
                  tags=sorted({t for s in specs for t in s.tags}),
                  models=sorted({s.model for s in specs}),
                  states=["online", "offline", "unchecked", "running"],
                  chosen={"tag": tag, "model": model, "state": state, "q": q},
                  view="table" if view == "table" else "grid",
                  check_every_s=settings.machine_check_interval_s,
                  refresh_s=FLEET_REFRESH_S)


@router.post("/check")
@audited_as("check fleet")
def check_fleet(request: Request, session: SessionDep, settings: SettingsDep,
                who: Reader) -> Response:
    specs = registry.list_all(session=session)
    audit(request, session, who, action="check fleet", detail={"machines": len(specs)})
    session.commit()  # no transaction open while the machines answer
    check_now(settings, specs)
    return RedirectResponse("/", status_code=303)


@router.post("/m/{machine_id}/check")
@audited_as("check machine")
def check_machine(request: Request, session: SessionDep, settings: SettingsDep,
                  machine_id: str, who: Reader) -> Response:
    spec = registry.get(session=session, machine_id=machine_id)
    audit(request, session, who, action="check machine", target=machine_id)
    session.commit()  # no transaction open while the machine answers
    check_now(settings, [spec])
    return RedirectResponse(f"/m/{machine_id}", status_code=303)


def _listing(files: MachineFiles, folder: str | None) -> dict[str, Any]:
    """One folder's subfolders and files with size and date."""
    place = files.paths.resolve(folder or None, None)
    listed = files.list_program_dir(folder or None, None)
    found = [{"name": files.paths.listed_name(w.entry.name), "size": w.entry.size,
              "mtime": w.entry.mtime} for w in files.walk(place, recursive=False)]
    here = files.paths.display(place)
    parent = files.paths.display(Place(place.root, place.parts[:-1])) if place.parts else None
    return {"here": here, "parent": parent, "files": found,
            "folders": [{"name": d, "dir": files.paths.display(Place(place.root,
                                                                     place.parts + (d,)))}
                        for d in listed["subDirs"]]}


@router.get("/m/{machine_id}", response_class=HTMLResponse)
def machine(request: Request, session: SessionDep, settings: SettingsDep, who: ViewerDep,
            machine_id: str, dir: str = "") -> Response:
    spec = registry.get(session=session, machine_id=machine_id)
    row = registry.governing_row(spec)
    jobs_of = service.list_jobs(session=session, machine_id=machine_id, limit=20)
    backups = list(session.scalars(
        select(Backup).where(select(BackupMachine.id).where(
            BackupMachine.backup_id == Backup.id,
            BackupMachine.machine_id == machine_id).exists())
        .order_by(Backup.created_at.desc()).limit(20)))
    runs_of = run_views.list_runs(session=session, machine_id=machine_id, limit=20)
    listing, error = None, None
    try:
        with opened(session, settings, machine_id, wait_s=PAGE_WAIT_S, reading=True) as files:
            listing = _listing(files, dir)
    except ContractError as exc:
        error = f"{int(exc.code)} {exc.status_msg or exc.code.name}"
    return render(request, who, "machine.html", spec=spec.public(), roots=list(row.roots),
                  can=door.abilities(spec), listing=listing, error=error, dir=dir,
                  jobs=[job_views.view(session=session, job=j) for j in jobs_of],
                  backups=backups, runs=[run_views.view(r) for r in runs_of],
                  check=checks.last(session, machine_id),
                  may_files=who.may(Role.OPERATOR) and who.principal.may_touch(machine_id),
                  message=request.query_params.get("message"))


def _back(machine_id: str, folder: str, message: str) -> RedirectResponse:
    return RedirectResponse(f"/m/{machine_id}?{urlencode({'dir': folder, 'message': message})}",
                            status_code=303)


@router.post("/m/{machine_id}/upload")
@audited_as("send file", status_of=library_status)
def upload(request: Request, session: SessionDep, settings: SettingsDep, who: Operator,
           machine_id: str, file: Annotated[UploadFile, File()],
           dir: Annotated[str, Form()] = "") -> Response:
    data = file.file.read()
    name = file.filename or "PROGRAM"

    def send(files: MachineFiles) -> None:
        files.send(files.send_ref(name, dir or None, None, data[:FANUC_HEAD_BYTES]),
                   io.BytesIO(data))

    return _change(request, session, settings, who, machine_id, dir, name, send,
                   action="send file", done=f"Sent {name} ({len(data)} bytes).",
                   refused="Not sent")


@router.post("/m/{machine_id}/delete")
@audited_as("delete file", status_of=library_status)
def delete_file(request: Request, session: SessionDep, settings: SettingsDep, who: Operator,
                machine_id: str, name: Annotated[str, Form()],
                dir: Annotated[str, Form()] = "") -> Response:
    return _change(request, session, settings, who, machine_id, dir, name,
                   lambda files: files.delete(files.ref(name, dir or None, None)),
                   action="delete file", done=f"Deleted {name}.", refused="Not deleted")


@router.post("/m/{machine_id}/mkdir")
@audited_as("make folder", status_of=library_status)
def make_folder(request: Request, session: SessionDep, settings: SettingsDep, who: Operator,
                machine_id: str, name: Annotated[str, Form()],
                dir: Annotated[str, Form()] = "") -> Response:
    return _change(request, session, settings, who, machine_id, dir, name,
                   lambda files: files.make_dir(name, dir or None, None),
                   action="make folder", done=f"Made the folder {name}.",
                   refused="No folder made")


def _change(request: Request, session: Session, settings: Settings, who: Viewer,
            machine_id: str, folder: str, name: str, act: Callable[[MachineFiles], object],
            *, action: str, done: str, refused: str) -> Response:
    """One change to a machine's files from its page: allowed for this viewer, made under
    one of the machine's slots, told on the page it came from, and audited."""
    who.may_change([machine_id])
    status = 200
    try:
        with opened(session, settings, machine_id) as files:
            act(files)
        message = done
    except ContractError as exc:  # as the API's upload to a machine answers: 404, 400, 413, 409
        message, status = f"{refused}: {said(exc)}", library_status(exc)
    audit(request, session, who, action=action, target=f"{machine_id}:{folder}/{name}",
          status=status)
    return _back(machine_id, folder, message)


@router.get("/m/{machine_id}/download")
def download(session: SessionDep, settings: SettingsDep, who: ViewerDep, machine_id: str,
             name: str, dir: str = "") -> Response:
    with opened(session, settings, machine_id, reading=True) as files:
        data = files.read_bytes(files.ref(name, dir or None, None), max_bytes=DOWNLOAD_MAX_BYTES)
    # RFC 6266: the name itself in UTF-8, with an ASCII one for clients that read no other
    # (a header's raw bytes beyond ASCII are read differently, or refused, everywhere).
    plain = "".join(c if c.isascii() and (c.isalnum() or c in "._-") else "_" for c in name)
    return Response(data, media_type="application/octet-stream", headers={
        "Content-Disposition": f"attachment; filename=\"{plain}\"; "
                               f"filename*=UTF-8''{quote(name, safe='')}"})
