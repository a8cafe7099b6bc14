"""Restores from stored backups: which files, each checked, and their bytes as a stream.

A restore is a send job whose targets name members of a backup ZIP; the runner reads each
member in chunks as it sends it, so no file is ever held whole, whatever its size.
"""

from __future__ import annotations

import contextlib
import hashlib
import zipfile
from collections.abc import Callable, Collection, Generator, Iterator
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs import service
from jobs.backup import manifests, store
from jobs.backup_models import Backup, BackupFile, MachineBackupStatus
from jobs.db import session_scope
from jobs.errors import ContractError, ErrorCode, first_named, hint
from jobs.fleet import door, registry
from jobs.fleet.paths import MachinePaths, Place
from jobs.settings import Settings
from worker.transports.base import CHUNK_BYTES


@dataclass(frozen=True)
class RestoreFile:
    """A file of a backup to send back: where it was and where it is in the ZIP."""

    path: str  # on the machine, as it wrote it
    archive_path: str
    sha256: str
    size: int
    machine_id: str  # whose listing named it


def _none_of(backup: Backup, machine_id: str) -> str:
    """Why the backup holds no file of the machine: it failed there, or was not asked."""
    of = f"backup {backup.id} holds no file of {machine_id}"
    machine = next((m for m in backup.machines if m.machine_id == machine_id), None)
    if machine is None:
        return f"{of}: it backed up {first_named([m.machine_id for m in backup.machines], 10)}"
    if machine.status is MachineBackupStatus.OK:
        return f"{of}: its folders were empty"
    return f"{of}: its backup {machine.status.value} ({machine.error_code} {machine.error_msg})"


def restore_files(*, settings: Settings, backup: Backup, machine_id: str,
                  path: str | None = None, paths: MachinePaths | None = None) -> list[RestoreFile]:
    """The machine's files in the backup, below `path` if given, each read once in chunks
    and checked against the manifest's SHA-256 before anything is sent.

    `path` is a file or folder as the backup holds it (`//CNC_MEM/O1234`) or as the
    machine's rules `paths` read a dirAtCNC and fileName: relative to its default root, as
    `dncq backup show` lists it (`O1234`, `USER`), a Fanuc program by its number (`1234`).
    A folder ends at the model's separator only (`/sub/a` holds no `/sub/a\\b.nc` on a
    machine of `/` folders); without `paths` (the machine is gone) at either.

    Raises 158 when there is nothing to restore (naming the closest path held) or the ZIP
    is missing, 20016 when a member is damaged.
    """
    separator = paths.row.separator if paths else None
    ends = (separator,) if separator else ("/", "\\")
    folder, file = _as_held(path, paths) if path else ("", "")
    below = tuple(folder.rstrip("".join(ends)) + end for end in ends) if path else ()
    held = [f for f in backup.files if f.machine_id == machine_id]
    chosen = [RestoreFile(f.path, f.archive_path, f.sha256, f.size, f.machine_id)
              for f in held
              if not path or f.path in (folder, file) or f.path.startswith(below)]
    if not held:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, _none_of(backup, machine_id))
    if not chosen:
        shown = [f.path for f in held] + [_below_root(f.path, paths) for f in held]
        raise ContractError(ErrorCode.PATH_NOT_FOUND,
                            f"backup {backup.id} holds nothing of {machine_id} at {path or '/'}"
                            f"{hint(path, shown) if path else ''}")
    zip_path = store.backup_dir(settings) / backup.name
    with _opened(zip_path) as archive:
        for f in chosen:
            for _chunk in _member_chunks(archive, f):
                pass  # read to check it, nothing kept
    return chosen


def _as_held(path: str, paths: MachinePaths | None) -> tuple[str, str]:
    """`path` as a folder and as a file, in the model's notation as the backup holds them;
    as written when the machine is gone or its rules refuse it (`..`, a root it has not),
    which names nothing held."""
    try:
        place = paths.parse(path) if paths else None
    except ContractError:
        place = None
    if paths is None or place is None:
        return path, path
    folder = paths.display(place)
    if not place.parts:
        return folder, folder
    *parents, last = place.parts
    with contextlib.suppress(ContractError):  # a folder's name may be no file name (Siemens)
        return folder, paths.display(Place(place.root, (*parents, paths.stored_name(last))))
    return folder, folder


def _below_root(held: str, paths: MachinePaths | None) -> str:
    """A held path below the machine's default root as the ZIP names it (`USER/O2000`);
    a path of another root as held."""
    try:
        place = paths.parse(held) if paths else None
    except ContractError:  # the model's rules have changed since
        place = None
    return "/".join(place.parts) if place and paths and place.root == paths.default else held


def restore_targets(*, session: Session, settings: Settings, backup: Backup, machine_id: str,
                    path: str | None = None, to: str | None = None) -> list[service.TargetIn]:
    """The targets of a restore job: `machine_id`'s files in the backup (below `path`),
    each checked, sent back to it or to the machine `to`."""
    place = placement(session=session, machine_id=machine_id)
    spec = _registered(session, machine_id)
    paths = door.paths_of(spec) if spec else None
    separator = paths.row.separator if paths else None
    targets: list[service.TargetIn] = []
    for f in restore_files(settings=settings, backup=backup, machine_id=machine_id, path=path,
                           paths=paths):
        folder, name = split_path(f.path, separator)  # the runners read each file from the ZIP
        dir_at_cnc, sub_dir = place(folder)
        targets.append(service.TargetIn(machineID=to or machine_id, fileName=name,
                                        dirAtCNC=dir_at_cnc, subDir=sub_dir,
                                        archivePath=f.archive_path))
    return targets


def placement(*, session: Session, machine_id: str
              ) -> Callable[[str], tuple[str | None, str | None]]:
    """How a backed-up folder is named to the machine a restore sends to.

    A folder below the backed-up machine's default root goes as a `subDir` (no folder at
    all for a file in the root), so that it lands below the default root of whichever
    machine receives it, even a model that takes no target folder (Fanuc 18i) or writes
    its root another way; a folder of another root is sent as it was written.
    """
    spec = _registered(session, machine_id)
    if spec is None:  # the backed-up machine is gone: the folders as written
        return lambda folder: (folder or None, None)
    paths = door.paths_of(spec)

    def place(folder: str) -> tuple[str | None, str | None]:
        try:
            found = paths.parse(folder) if folder else None
        except ContractError:
            return folder, None
        if found is None or found.root != paths.default:
            return folder or None, None
        return None, "/".join(found.parts) or None

    return place


def separators_of(*, session: Session, machine_ids: Collection[str]) -> dict[str, str | None]:
    """The folder separator of each machine's model (None for one gone), in one read of the
    registry."""
    found = registry.of_ids(session=session, machine_ids=machine_ids)
    return {m: door.paths_of(found[m]).row.separator if m in found else None
            for m in machine_ids}


def _registered(session: Session, machine_id: str) -> registry.MachineSpec | None:
    """The machine, or None once removed (asked of every machine a backup holds: no
    registry.get, whose refusal reads the whole fleet for a hint)."""
    return registry.of_ids(session=session, machine_ids=[machine_id]).get(machine_id)


def split_path(machine_path: str, separator: str | None = None) -> tuple[str, str]:
    """A machine path into its folder (as the model writes it) and file name.

    With the model's `separator`, a `\\` in a name on a machine whose folders are split by
    `/` stays in the name (a Unix FTP server stores `a\\b.nc`); without, either splits.
    """
    cut = (machine_path.rfind(separator) if separator
           else max(machine_path.rfind("/"), machine_path.rfind("\\")))
    return machine_path[:cut + 1], machine_path[cut + 1:]


def find_member(*, settings: Settings, backup_id: str, archive_path: str
                ) -> tuple[Path, RestoreFile]:
    """The ZIP and the file of a restore target; 158 when either is gone."""
    with session_scope(settings.resolved_database_url) as session:
        backup = manifests.get(session=session, backup_id=backup_id)
        found = session.scalar(select(BackupFile).where(
            BackupFile.backup_id == backup_id, BackupFile.archive_path == archive_path))
        if found is None:
            raise ContractError(ErrorCode.PATH_NOT_FOUND,
                                f"backup {backup_id} holds no {archive_path}")
        return (store.backup_dir(settings) / backup.name,
                RestoreFile(found.path, found.archive_path, found.sha256, found.size,
                            found.machine_id))


def read_member(zip_path: Path, f: RestoreFile) -> Generator[bytes, None, None]:
    """A restored file's bytes, in chunks, read from the ZIP as they are taken.

    The chunks raise 20016 before the last one when the bytes differ from the manifest's
    SHA-256, so a transport writing them never completes the file.
    """
    with _opened(zip_path) as archive:
        yield from _member_chunks(archive, f)


@contextlib.contextmanager
def _opened(zip_path: Path) -> Iterator[zipfile.ZipFile]:
    try:
        archive = zipfile.ZipFile(zip_path)
    except FileNotFoundError:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"{zip_path.name} is missing") from None
    except (OSError, zipfile.BadZipFile) as exc:
        raise _damaged(zip_path.name, exc) from None
    with archive:
        yield archive


def _member_chunks(archive: zipfile.ZipFile, f: RestoreFile) -> Iterator[bytes]:
    """The member's bytes; 20016 instead of the last chunk when they are not the manifest's."""
    digest, size = hashlib.sha256(), 0
    try:
        with archive.open(f.archive_path) as member:
            held = member.read(CHUNK_BYTES)
            while held:
                digest.update(held)
                size += len(held)
                following = member.read(CHUNK_BYTES)  # its CRC is checked at the end
                if not following:
                    break
                yield held
                held = following
    except manifests.DAMAGED as exc:
        raise _damaged(f.archive_path, exc) from None
    if size != f.size or digest.hexdigest() != f.sha256:
        raise _damaged(f.archive_path, "its SHA-256 differs from the manifest")
    if held:
        yield held


def _damaged(what: str, why: object) -> ContractError:
    return ContractError(ErrorCode.VERIFY_MISMATCH,
                         f"{what} in the backup is damaged ({why}); nothing was restored")
