"""Stored backups as the API shows them: one by id, its manifest with each failed
machine's own words, a re-read of its ZIP, and what changed between two."""

from __future__ import annotations

import hashlib
import zipfile
import zlib
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs.backup_models import Backup, MachineBackupStatus
from jobs.errors import ContractError, ErrorCode
from jobs.folders import backup_dir
from jobs.models import Target, TargetState
from jobs.settings import Settings


def get(*, session: Session, backup_id: str) -> Backup:
    """The backup, or a 404-worthy error."""
    backup = session.get(Backup, backup_id)
    if backup is None:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no backup {backup_id}")
    return backup


def view(backup: Backup, *, session: Session | None = None) -> dict[str, Any]:
    """A backup as the API shows it; given a session, each machine with `statusMsg` too:
    what its failed target said beyond the contract's words (null when none failed, or once
    the job that made the backup is deleted)."""
    said = failure_details(session=session, job_id=backup.job_id) if session else {}
    return {"id": backup.id, "job": backup.job_id, "name": backup.name,
            "status": backup.status.value, "size": backup.size, "sha256": backup.sha256,
            "createdAt": backup.created_at,
            "machines": [{"machineID": m.machine_id, "machineName": m.machine_name,
                          "status": m.status, "errorCode": m.error_code,
                          "errorMsg": m.error_msg, "leftOut": m.left_out or [],
                          **({"statusMsg": said.get(m.machine_id)} if session else {})}
                         for m in backup.machines],
            "files": backup.file_count}


def manifest(*, session: Session, backup: Backup) -> dict[str, Any]:
    """The manifest as the database keeps it: the backup's view, with `statusMsg`, and
    every file."""
    return {**view(backup, session=session), "files": [
        {"machineID": f.machine_id, "path": f.path, "archivePath": f.archive_path,
         "size": f.size, "mtime": f.mtime, "sha256": f.sha256} for f in backup.files]}


def verify(*, settings: Settings, backup: Backup) -> list[str]:
    """Problems found re-reading the ZIP (every CRC and every SHA-256); empty when sound."""
    path = backup_dir(settings) / backup.name
    problems: list[str] = []
    try:
        with zipfile.ZipFile(path) as archive:
            for f in backup.files:
                try:
                    if _sha256_of(archive, f.archive_path) != f.sha256:
                        problems.append(f"{f.archive_path}: SHA-256 differs from the manifest")
                except DAMAGED as exc:  # one bad member: say so and go on with the others
                    problems.append(f"{f.archive_path}: {type(exc).__name__}: {exc}")
    except (OSError, zipfile.BadZipFile) as exc:
        problems.append(f"{backup.name}: {exc}")
    return problems


# What reading a damaged member raises: a bad CRC, bad deflate data, a cut-off file.
DAMAGED = (zipfile.BadZipFile, zlib.error, EOFError, KeyError, OSError)


def _sha256_of(archive: zipfile.ZipFile, name: str) -> str:
    digest = hashlib.sha256()
    with archive.open(name) as member:  # its CRC is checked at the end
        while chunk := member.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def failure_details(*, session: Session, job_id: str | None) -> dict[str, str]:
    """Per machine, what its first failed target said (the FTP server's refusal, the
    backups folder's error), from the job that made the backup: the target its errorMsg
    names (jobs.backup.store), so a later one's words are not given for it."""
    found = session.execute(select(Target.machine_id, Target.status_msg).where(
        Target.job_id == job_id, Target.state == TargetState.FAILED).order_by(
        Target.position.desc()))
    first: dict[str, str | None] = {machine_id: said for machine_id, said in found}
    return {machine_id: said for machine_id, said in first.items() if said}


ABSENT = "absent"  # a machine that a backup compared does not hold at all


def diff(*, first: Backup, second: Backup, machine_id: str | None = None
         ) -> dict[str, dict[str, Any]]:
    """Per machine: files added, removed and changed from `first` to `second`, and
    `incomplete`, the backups (of the two) that do not hold all of its files, by id, with
    why (`partial`, `failed`, or `absent`: the machine is not in it)."""
    def index(b: Backup) -> dict[str, dict[str, str]]:
        found: dict[str, dict[str, str]] = {}
        for f in b.files:
            if machine_id is None or f.machine_id == machine_id:
                found.setdefault(f.machine_id, {})[f.path] = f.sha256
        return found

    def statuses(b: Backup) -> dict[str, str]:
        return {m.machine_id: m.status.value for m in b.machines
                if machine_id is None or m.machine_id == machine_id}

    old, new = index(first), index(second)
    old_status, new_status = statuses(first), statuses(second)
    result: dict[str, dict[str, Any]] = {}
    asked = {machine_id} if machine_id else set()  # named, it is answered for, held or not
    for machine in sorted(set(old_status) | set(new_status) | asked):
        a, b = old.get(machine, {}), new.get(machine, {})
        incomplete = {backup.id: status.get(machine, ABSENT)
                      for backup, status in ((first, old_status), (second, new_status))
                      if status.get(machine) != MachineBackupStatus.OK}
        # A file missing from a backup that does not hold the whole machine is unknown
        # there, not added or removed: only what both hold is compared.
        result[machine] = {
            "added": [] if first.id in incomplete else sorted(set(b) - set(a)),
            "removed": [] if second.id in incomplete else sorted(set(a) - set(b)),
            "changed": sorted(p for p in set(a) & set(b) if a[p] != b[p]),
            "incomplete": incomplete}
    return result

