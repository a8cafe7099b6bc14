"""Where a machine's requests find programs: its source folders, in order, first match wins.

A source is a library folder (`library:VIPROS`: the approved version of each program) or a
folder on any machine dncq reaches (`machine:1010:/NC`: read under that machine's lease,
like any single-machine request). A request's relative folder (`(DIR=/VIPROS)`) is taken
below each source's folder. A folder on the requesting machine itself is read under the
lease its caller holds already (`held`): a second slot would wait for that caller.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TypeVar

from jobs import db
from jobs.db import session_scope
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import door, registry
from jobs.fleet.request_settings import Source
from jobs.fleet.rules import MachineFiles
from jobs.library import blobs
from jobs.library import service as library
from jobs.library.names import check_folder
from jobs.requests.answers import ListedFile
from jobs.run import leases
from jobs.settings import Settings

T = TypeVar("T")
MACHINE_WAIT_S = 30.0  # how long a request waits for a source machine's slot
MAX_PROGRAM_BYTES = 16 * 1024 * 1024  # a program sent in answer is read whole


@dataclass(frozen=True)
class Found:
    """A program found in a source: its bytes and where, in words (`library VIPROS/0010`)."""

    data: bytes
    where: str


def _missing(folder: str, name: str) -> ContractError:
    shown = f"{folder}/{name}" if folder else name
    return ContractError(ErrorCode.PATH_NOT_FOUND, f"NOT FOUND: {shown}")


def _library_folder(source: Source, folder: str) -> str:
    """The library folder of `folder` in the source; the top holds no programs (158)."""
    joined = "/".join(p for p in (source.folder.strip("/"), folder.strip("/")) if p)
    if not joined:
        raise ContractError(ErrorCode.PATH_NOT_FOUND,
                            "the library's top holds folders, not programs")
    return check_folder(joined)


@contextlib.contextmanager
def _machine(settings: Settings, source: Source, held: str | None) -> Iterator[MachineFiles]:
    """The source machine's files, under a slot of its own unless its lease is `held`."""
    url = settings.resolved_database_url
    with session_scope(url) as session:
        spec = registry.get(session=session, machine_id=source.machine_id or "")
    slot = (contextlib.nullcontext() if spec.id == held else
            leases.hold(url, machine_id=spec.id, max_concurrent=spec.max_concurrent,
                        wait_s=MACHINE_WAIT_S, ttl_s=settings.lease_ttl_s))
    with slot:
        files = door.open_files(spec, data_dir=settings.data_dir)
        try:
            yield files
        finally:
            files.close()


def _machine_dir(source: Source, folder: str) -> str:
    return "/".join(p for p in (source.folder.rstrip("/"), folder.strip("/")) if p) or "/"


def _first(sources: list[Source], folder: str, name: str,
           attempt: Callable[[Source], T | None]) -> T:
    """`attempt` on each source in order: the first answer that is not None; a source that
    has no such program or folder (158, or None) passes to the next; 158 when none has."""
    for source in sources:
        try:
            answer = attempt(source)
        except ContractError as exc:
            if exc.code is not ErrorCode.PATH_NOT_FOUND:
                raise
            continue
        if answer is not None:
            return answer
    raise _missing(folder, name)


def find(settings: Settings, sources: list[Source], folder: str, name: str, *,
         held: str | None = None) -> Found:
    """The program `folder/name` of the first source that has it; 158 when none has.

    Args:
        held: the machine whose lease the caller holds (the one that asks).
    """
    def attempt(source: Source) -> Found | None:
        if source.kind == "library":
            with session_scope(settings.resolved_database_url) as session:
                lib_folder, lib_name = library.spelled(
                    session=session, folder=_library_folder(source, folder), name=name)
                chosen = library.approved(library.find(session=session, folder=lib_folder,
                                                       name=lib_name))
                if chosen is None:
                    return None  # not approved yet: not for a machine
                sha = chosen.sha256
            return Found(blobs.read_all(settings, sha), f"library {lib_folder}/{lib_name}")
        with _machine(settings, source, held) as files:
            ref = files.ref(name, _machine_dir(source, folder), None)
            data = files.read_bytes(ref, max_bytes=MAX_PROGRAM_BYTES)
            return Found(data, f"machine {source.machine_id} {files.display_path(ref)}")

    return _first(sources, folder, name, attempt)


def listing(settings: Settings, sources: list[Source], folder: str, *,
            held: str | None = None) -> list[ListedFile]:
    """The programs of `folder` in every source, by name; a name in two shows the first."""
    seen: dict[str, ListedFile] = {}
    found_folder = False
    for source in sources:
        try:
            for entry in _list_one(settings, source, folder, held):
                seen.setdefault(entry.name, entry)
            found_folder = True
        except ContractError as exc:
            if exc.code is not ErrorCode.PATH_NOT_FOUND:
                raise
    if not found_folder and folder:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"NOT FOUND: {folder}")
    return sorted(seen.values(), key=lambda e: e.name)


def _list_one(settings: Settings, source: Source, folder: str,
              held: str | None) -> list[ListedFile]:
    if source.kind == "library":
        with session_scope(settings.resolved_database_url) as session:
            lib_folder = library.spelled_folder(session=session,
                                                folder=_library_folder(source, folder))
            shown = []
            for program in library.list_programs(session=session, folder=lib_folder):
                chosen = library.approved(program)
                if program.folder == lib_folder and chosen is not None:
                    shown.append(ListedFile(program.name, chosen.size, chosen.created_at))
        if not shown and not _library_has(settings, lib_folder):
            raise _missing(folder, "")
        return shown
    with _machine(settings, source, held) as files:
        place = files.paths.resolve(_machine_dir(source, folder), None)
        return [ListedFile(files.paths.listed_name(f.entry.name), f.entry.size or 0,
                           _when(f.entry.mtime))
                for f in files.walk(place, recursive=False)]


def _library_has(settings: Settings, folder: str) -> bool:
    """Whether any program (of any state) is in `folder` or below: the folder exists."""
    with session_scope(settings.resolved_database_url) as session:
        return bool(library.list_programs(session=session, folder=folder))


def _when(mtime: float | None) -> datetime | None:
    return datetime.fromtimestamp(mtime, UTC) if mtime else None


def delete(settings: Settings, sources: list[Source], folder: str, name: str, *,
           by: str, held: str | None = None) -> str:
    """Delete `folder/name` from the first source that has it; where, in words."""
    def attempt(source: Source) -> str:
        if source.kind == "library":
            with session_scope(settings.resolved_database_url) as session:
                db.write_first(session)  # SQLite: one delete or rename at a time, as below
                lib_folder, lib_name = library.spelled(
                    session=session, folder=_library_folder(source, folder), name=name)
                # Held: of two controls deleting it at once, the second is told NOT FOUND
                program = library.find(session=session, folder=lib_folder, name=lib_name,
                                       for_update=True)
                if library.approved(program) is None:  # never listed nor sent to a machine
                    raise _missing(folder, name)
                library.delete(session=session, folder=lib_folder, name=lib_name)
            return f"library {lib_folder}/{lib_name}"
        with _machine(settings, source, held) as files:
            ref = files.ref(name, _machine_dir(source, folder), None)
            files.delete(ref)
            return f"machine {source.machine_id} {files.display_path(ref)}"

    return _first(sources, folder, name, attempt)


def rename(settings: Settings, sources: list[Source], folder: str, name: str, new_name: str,
           *, by: str, held: str | None = None) -> str:
    """Rename `folder/name` to `new_name` in the first source that has it; where, in words.

    A library program is renamed as a new program holding the old one's approved version,
    then its newer versions waiting for review (the old one is deleted, its history kept);
    a machine's file is written under the new name and then removed under the old, so
    nothing is lost if either step fails.
    """
    def attempt(source: Source) -> str:
        if source.kind == "library":
            return _rename_in_library(settings, source, folder, name, new_name, by=by)
        with _machine(settings, source, held) as files:
            place = _machine_dir(source, folder)
            old, new = files.ref(name, place, None), files.ref(new_name, place, None)
            data = files.read_bytes(old, max_bytes=MAX_PROGRAM_BYTES)
            files.send_chunks(new, iter([data]))
            files.delete(old)
            return f"machine {source.machine_id} {files.display_path(new)}"

    return _first(sources, folder, name, attempt)


def _rename_in_library(settings: Settings, source: Source, folder: str, name: str,
                       new_name: str, *, by: str) -> str:
    with session_scope(settings.resolved_database_url) as session:
        db.write_first(session)  # SQLite: one delete or rename at a time
        lib_folder, name = library.spelled(session=session,
                                           folder=_library_folder(source, folder), name=name)
        # Both names held to the commit: a program renamed by two requests at once gets one
        # new name, and two renamed onto one name at once do not become one's versions.
        program = library.find(session=session, folder=lib_folder, name=name, for_update=True)
        chosen = library.approved(program)
        if chosen is None:  # never listed nor sent to a machine: not there, as for a delete
            raise _missing(folder, name)
        if new_name == name:  # renamed onto itself: nothing moves, and nothing is deleted
            return f"library {lib_folder}/{name}"
        # Taken in any case, as requests find names: two programs that differ in case only
        # would leave both unfound in any other (a case-only rename of itself is free).
        _, taken = library.spelled(session=session, folder=lib_folder, name=new_name)
        if taken != name and library.holds(session=session, folder=lib_folder, name=taken):
            raise ContractError(ErrorCode.PATH_EXISTS, f"EXISTS: {lib_folder}/{taken}")
        library.hold_name(session=session, folder=lib_folder, name=new_name)
        library.add(session=session, folder=lib_folder, name=new_name,
                    blob=blobs.BlobInfo(chosen.sha256, chosen.size),
                    note=f"renamed from {name} by a request", created_by=by,
                    source=f"rename of {program.path}",
                    approve=True)
        for waiting in library.waiting_after(program, chosen):  # still to be reviewed there
            library.add(session=session, folder=lib_folder, name=new_name,
                        blob=blobs.BlobInfo(waiting.sha256, waiting.size), note=waiting.note,
                        created_by=waiting.created_by,
                        source=f"rename of {program.path} v{waiting.number}")
        library.delete(session=session, folder=lib_folder, name=name)
    return f"library {lib_folder}/{new_name}"
