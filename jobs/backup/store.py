"""Stored backups: backup jobs fetched per target, then assembled into one ZIP.

A backup job is a batch job of kind `backup`: each target's runner deflates its machine's
files into one work file, `<backup_dir>/.work/<job>/<target>.spool` (a shared folder when
workers run on several hosts), followed by its record (the deflate drops the GIL, so it
spreads over the cores). When the job's last target is final, one assembler copies those
bytes into `BackupFiles_<date>-<job>.zip` (a temporary name of its own, fsync, then a hard
link, so no ZIP is ever replaced) and registers it with its manifest. Best effort: a
machine that failed is recorded, the others are kept. Reading what was stored (manifests,
verify, diff) is jobs.backup.manifests; restoring it, jobs.backup.restore.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import os
import shutil
import struct
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO, cast

from sqlalchemy import Table, insert, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from jobs.backup import archive_names, streamed
from jobs.backup.zipwriter import DEFLATED, PreparedMember, deflated, joined, write_zip
from jobs.backup_models import Backup, BackupFile, BackupMachine, BackupStatus, MachineBackupStatus
from jobs.db import held, insert_rows, session_scope
from jobs.errors import MESSAGES, ContractError, ErrorCode
from jobs.fleet import registry
from jobs.fleet.rules import MachineFiles
from jobs.folders import (
    ASSEMBLING,
    backup_dir,
    being_assembled,
    job_folder,
    private_dir,
    private_opener,
)
from jobs.models import Job, JobKind, Machine, Target, TargetState
from jobs.run import settle
from jobs.settings import Settings
from worker.transports import parts

log = logging.getLogger(__name__)

RECORD_LENGTH = struct.Struct("<Q")  # the last bytes of a target's spool file
WRITTEN_BYTES = 256 * 1024  # the ZIP goes to its file in pieces of this size


def work_file(settings: Settings, job_id: str, target_id: int) -> Path:
    """Where one target's files wait for the assembler: deflated one after another, then
    their record (JSON), then the record's length.

    One file a target, in the job's folder: a folder and a record file of its own would be
    three creations more, each a round trip on a data folder shared over the network.
    """
    return job_folder(settings, job_id) / f"{target_id}.spool"


def fetch_target(settings: Settings, files: MachineFiles, *, job_id: str, target_id: int,
                 machine_id: str, params: dict[str, Any]) -> int:
    """A backup job's target: its files into its work file; returns how many."""
    target = streamed.BackupTarget(machineID=machine_id, **params)
    checked = streamed.check_one(files, target, probe=False)  # the fetch finds what is missing
    spool = work_file(settings, job_id, target_id)
    fetched: dict[str, streamed.Fetched] = {}
    files.left_out.clear()
    try:
        spool.parent.mkdir(parents=True, exist_ok=True)
        spool.unlink(missing_ok=True)  # an earlier, interrupted attempt
        streamed.fetch(files, checked, spool, fetched, level=settings.backup_zip_level)
        records = [vars(f) for f in fetched.values()]
        record = json.dumps({
            "files": records, "leftOut": [streamed.left_out_entry(x) for x in files.left_out]
        }).encode()
        with open(spool, "ab") as out:
            out.write(record + RECORD_LENGTH.pack(len(record)))
    except OSError as exc:
        with contextlib.suppress(OSError):
            spool.unlink(missing_ok=True)  # no half-written work file left behind
        if not _of_the_folder(settings, exc):  # the machine's, which its transport missed
            raise ContractError(ErrorCode.CONNECTION_FAILED, exc.strerror or str(exc)) from exc
        raise folder_failed(settings, exc) from exc
    return len(records)


def _of_the_folder(settings: Settings, exc: OSError) -> bool:
    """Whether the backups folder failed (the machine's failures come as ContractError): a
    path in it, or a write that found no room or no leave (a write's error names no file)."""
    if exc.filename is not None:
        return Path(os.fsdecode(exc.filename)).is_relative_to(backup_dir(settings))
    return exc.errno in _DISK_FAILURES


_DISK_FAILURES = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG, errno.EIO}


def folder_failed(settings: Settings, exc: OSError) -> ContractError:
    """20017 for the backups folder failing (full, read-only), naming it and the error."""
    return ContractError(ErrorCode.INTERNAL_ERROR,
                         f"backups folder {backup_dir(settings)}: {exc.strerror or exc}")


def _read_record(spool: BinaryIO) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """A fetched target's files and what it left out, from the end of its work file."""
    spool.seek(-RECORD_LENGTH.size, os.SEEK_END)
    (length,) = RECORD_LENGTH.unpack(spool.read(RECORD_LENGTH.size))
    spool.seek(-RECORD_LENGTH.size - length, os.SEEK_END)
    record = json.loads(spool.read(length))
    return record["files"], record["leftOut"]


def assemble(*, settings: Settings, job_id: str) -> str | None:
    """Write the job's ZIP and register it; the id of the job's backup, also one an earlier
    delivery or another assembly registered (None if the job is not a stored backup).

    What follows a registration (a schedule's retention and alerts) is the caller's step,
    taken by every delivery: the store knows nothing of schedules, and the step itself
    knows whether it was taken (jobs.backup.follow_up.after_backup).
    """
    url = settings.resolved_database_url
    with session_scope(url) as session:
        job = session.get(Job, job_id)
        if job is None or job.kind is not JobKind.BACKUP or job.options.get("streamed"):
            return None  # a streamed job's ZIP went to its client (jobs.backup.download)
        done = session.scalar(select(Backup.id).where(Backup.job_id == job_id))
        if done:
            return done  # the task was delivered twice
        if being_assembled(settings, job_id):
            # Another delivery writes the ZIP (a second beside it is twice the room and the
            # disk's time): it registers the backup, or fails and says why; if its writer
            # dies, the reaper asks again.
            log.info("backup job %s: another assembly writes its ZIP; left to that one", job_id)
            return None
        rows = [(t.id, t.machine_id, t.state, t.error_code, t.error_msg) for t in job.targets]
        names = registry.column_of(session=session, column=Machine.name,
                                   machine_ids={row[1] for row in rows})
    now = datetime.now().astimezone()  # aware: the name reads it as local time, members as UTC
    backup_id = uuid.uuid4().hex[:16]
    name = archive_names.backup_name(now)  # the ZIP's top folder, as the contract names it
    folder = backup_dir(settings)
    machines_seen: dict[str, dict[str, Any]] = {}
    said_failed: set[str] = set()  # machines whose error is a failed target's
    for target_id, machine_id, state, code, msg in rows:
        entry = machines_seen.setdefault(machine_id, {
            "machineID": machine_id, "machineName": names.get(machine_id, ""),
            "status": MachineBackupStatus.OK,
            "errorCode": 0, "errorMsg": None, "targets": [], "files": [], "leftOut": []})
        if state is TargetState.SUCCEEDED:
            entry["targets"].append(target_id)  # only what was fetched whole goes in
        elif entry["status"] is MachineBackupStatus.OK or (
                state is TargetState.FAILED and machine_id not in said_failed):
            # The first failed target's, whose words statusMsg gives (manifests.
            # failure_details): why files are missing; a cancelled one's while none failed.
            entry.update(status=MachineBackupStatus.FAILED,
                         errorCode=code or int(ErrorCode.CANCELLED), errorMsg=msg or state.value)
            if state is TargetState.FAILED:
                said_failed.add(machine_id)
    for entry in machines_seen.values():  # one failed target keeps the others' files
        if entry["status"] is MachineBackupStatus.FAILED and entry["targets"]:
            entry["status"] = MachineBackupStatus.PARTIAL
    members = _members(settings, job_id, f"{name}/", list(machines_seen.values()), now,
                       settings.backup_zip_level)
    # This call's alone (its backup id), named after its process: an assembler killed
    # mid-write leaves its part, which the next assembly on this host removes.
    part = folder / parts.part_name(ASSEMBLING, f"{name}-{job_id}-{backup_id}.zip.part")
    digest, size = hashlib.sha256(), 0
    try:
        private_dir(folder)
        removed = parts.remove_parts_of_dead_writers(folder, ASSEMBLING)
        if removed:
            log.info("removed %d half-written backups of assemblers that were killed", removed)
        with open(part, "xb", opener=private_opener) as out:
            # Pieces of 256 KB, not a member's header and bytes apart: a quarter less time
            # for 1000 programs (36 against 27 ms), most of it per-piece calls.
            for chunk in joined(write_zip(members), WRITTEN_BYTES):
                out.write(chunk)
                digest.update(chunk)
                size += len(chunk)
            out.flush()
            os.fsync(out.fileno())
        zip_name = _place(part, folder, f"{name}-{job_id}", backup_id)
    except OSError as exc:  # full, read-only, a work file gone: a retry would fail alike
        if being_assembled(settings, job_id, besides=part.name):
            # A second delivery of this assembly still writes its ZIP (two need twice the
            # room): that one registers the backup, or fails and says why.
            log.warning("backup job %s: this assembly failed (%s) while another writes its "
                        "ZIP; left to that one", job_id, exc)
            return None
        return _unstored(settings, job_id, folder_failed(settings, exc), exc)
    finally:  # placed, or a work file gone, a full disk: no half ZIP left behind
        with contextlib.suppress(OSError):
            part.unlink(missing_ok=True)
    ok = sum(m["status"] is MachineBackupStatus.OK for m in machines_seen.values())
    some = sum(m["status"] is not MachineBackupStatus.FAILED for m in machines_seen.values())
    status = (BackupStatus.COMPLETE if ok == len(machines_seen)
              else BackupStatus.PARTIAL if some else BackupStatus.FAILED)
    try:
        with session_scope(url) as session:
            _record(session, backup_id, job_id, zip_name, status, size,
                    digest.hexdigest(), list(machines_seen.values()))
    except IntegrityError:  # another assembler registered this job first
        (folder / zip_name).unlink(missing_ok=True)
        with session_scope(url) as session:
            return session.scalar(select(Backup.id).where(Backup.job_id == job_id))
    _remove_unregistered(folder, job_id, zip_name)
    shutil.rmtree(job_folder(settings, job_id), ignore_errors=True)
    return backup_id


def _remove_unregistered(folder: Path, job_id: str, registered: str) -> None:
    """Remove the job's ZIPs other than `registered`: an earlier delivery placed them and
    was killed, or lost the database, before it registered them; none can be now."""
    for stray in (*folder.glob(f"*-{job_id}.zip"), *folder.glob(f"*-{job_id}-*.zip")):
        if stray.name != registered:
            with contextlib.suppress(OSError):
                stray.unlink()


def _unstored(settings: Settings, job_id: str, error: ContractError,
              cause: OSError) -> str | None:
    """Record that the job's ZIP cannot be written, and raise `error`: the targets it
    fetched fail with it, the job is marked so that the reaper assembles it no more (its
    work folder may not be removable: a disk remounted read-only), and the work folder goes.
    The backup another assembler registered meanwhile, if one did, instead; None when an
    earlier assembly recorded the failure already (its alert went then)."""
    with session_scope(settings.resolved_database_url) as session:
        # One recording at a time, on SQLite too (FOR UPDATE takes no lock there)
        job = session.scalar(held(session, select(Job).where(Job.id == job_id)))
        first = session.scalar(select(Backup.id).where(Backup.job_id == job_id))
        if first is not None:
            return first
        if job is None or job.options.get("unstored"):
            return None
        job.options = {**job.options, "unstored": error.status_msg}
        session.execute(update(Target).where(
            Target.job_id == job_id, Target.state == TargetState.SUCCEEDED).values(
            state=TargetState.FAILED, error_code=int(error.code),
            error_msg=MESSAGES[error.code], status_msg=error.status_msg))
        settle.update_job_state(session=session, job_id=job_id)
    shutil.rmtree(job_folder(settings, job_id), ignore_errors=True)
    raise error from cause


def _place(part: Path, folder: Path, stem: str, backup_id: str) -> str:
    """Give the finished `part` its name in `folder` without replacing any ZIP; the name.

    `<stem>.zip` is the job's; a second delivery of the job assembling at the same time
    gets `<stem>-<backup id>.zip` (and removes it when the first one registered).
    """
    for zip_name in (f"{stem}.zip", f"{stem}-{backup_id}.zip"):
        try:
            _link_new(part, folder / zip_name)
            return zip_name
        except FileExistsError:
            continue
    raise FileExistsError(f"{folder / zip_name} is already there")


def _link_new(source: Path, target: Path) -> None:
    """`source` also as `target`, which must not exist (a hard link: atomic, never replaces)."""
    try:
        os.link(source, target)
    except FileExistsError:
        raise
    except OSError:  # a file system without hard links: claim the name, then move onto it
        os.close(os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
        os.replace(source, target)


def _members(settings: Settings, job_id: str, top: str, machine_entries: list[dict[str, Any]],
             now: datetime, level: int) -> Iterator[PreparedMember]:
    yield PreparedMember(top, now)
    folders = archive_names.machine_folders(
        [(entry["machineID"], entry["machineName"]) for entry in machine_entries])
    for entry, machine_folder in zip(machine_entries, folders, strict=True):
        if entry["status"] is MachineBackupStatus.FAILED:
            continue
        folder = top + machine_folder + "/"
        yield PreparedMember(folder, now)
        seen: set[str] = set()
        for target_id in entry["targets"]:
            yield from target_members(work_file(settings, job_id, target_id), folder, entry,
                                      seen, now)
    manifest = {"created": datetime.now(UTC).isoformat(), "job": job_id,
                "machines": [machine_manifest(m) for m in machine_entries]}
    body = json.dumps(manifest, indent=1).encode()
    yield deflated(top + archive_names.MANIFEST_NAME, now, body, level=level)


def target_members(work: Path, folder: str, entry: dict[str, Any], seen: set[str],
                   now: datetime) -> Iterator[PreparedMember]:
    """The ZIP members of one fetched target's work file, in `folder`; each file is added to
    its machine's `entry` (its `files` and `leftOut`), those in `seen` (named by an earlier
    target of the machine) skipped. The members only copy the work file's deflated bytes."""
    with open(work, "rb") as spool:
        records, left_out = _read_record(spool)
        streamed.add_left_out(entry, left_out)
        for record in records:
            if record["archive_path"] in seen:
                continue
            seen.add(record["archive_path"])
            record["archivePath"] = folder + record["archive_path"]
            entry["files"].append(record)
            when = datetime.fromtimestamp(record["mtime"], UTC) if record["mtime"] else now
            yield PreparedMember(
                record["archivePath"], when, record["crc32"], record["compressed_size"],
                record["size"], DEFLATED,
                streamed.read_slice(spool, record["offset"], record["compressed_size"]))


def machine_manifest(entry: dict[str, Any]) -> dict[str, Any]:
    """A machine's entry in the manifest: its status, what it left out, and its files."""
    return {k: v for k, v in entry.items() if k != "targets"} | {"files": [
        archive_names.manifest_file(f["machine_path"], f["archivePath"], f["size"],
                                    f["mtime"], f["sha256"]) for f in entry["files"]]}


def _record(session: Session, backup_id: str, job_id: str, name: str, status: BackupStatus,
            size: int, sha256: str, machine_entries: list[dict[str, Any]]) -> None:
    """Register the backup, then its machines and its files (by COPY on PostgreSQL: the
    ORM's objects for 50 machines were most of the registration's 21 ms)."""
    rows = [{"backup_id": backup_id, "machine_id": m["machineID"], "path": f["machine_path"],
             "archive_path": f["archivePath"], "size": f["size"], "mtime": f["mtime"],
             "sha256": f["sha256"]} for m in machine_entries for f in m["files"]]
    session.execute(insert(Backup).values(  # first: its machines and files refer to it
        id=backup_id, job_id=job_id, name=name, status=status, size=size, sha256=sha256,
        file_count=len(rows)))
    insert_rows(session, _BACKUP_MACHINES, [
        {"backup_id": backup_id, "position": position, "machine_id": m["machineID"],
         "machine_name": m["machineName"], "status": m["status"], "error_code": m["errorCode"],
         "error_msg": m["errorMsg"], "left_out": m.get("leftOut", [])}
        for position, m in enumerate(machine_entries)])
    insert_rows(session, _FILES, rows)


_BACKUP_MACHINES, _FILES = (cast(Table, m.__table__) for m in (BackupMachine, BackupFile))
