"""The library's operations: add, list, show, history, diff, restore, delete, decide, assign.

Programs are found by folder and name (jobs.library.names checks both); their bytes are
blobs (jobs.library.blobs), so a version costs a row and content is stored once however
many versions, programs or machines refer to it. A program's current version is its
highest-numbered one; its current approved version, what rollouts and listings use, is its
highest-numbered approved one.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterator
from dataclasses import dataclass

from sqlalchemy import func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, selectinload

from jobs import db
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.library import blobs
from jobs.library.models import LibraryAssignment, LibraryProgram, LibraryVersion, VersionState
from jobs.library.names import check_folder, check_program_name
from jobs.models import utcnow
from jobs.settings import Settings

DIFF_MAX_BYTES = 16 * 1024 * 1024  # each side of a diff is read whole: larger ones are refused


@dataclass(frozen=True)
class Added:
    """What `add` did: the version that holds the bytes, and whether it is a new one."""

    version: LibraryVersion
    created: bool  # False: the bytes were the program's current version already
    restored: bool = False  # the program was deleted, and is back


def _missing(what: str) -> ContractError:
    return ContractError(ErrorCode.PATH_NOT_FOUND, what)


def find(*, session: Session, folder: str, name: str, deleted: bool = False,
         for_update: bool = False) -> LibraryProgram:
    """The program `folder/name` (a deleted one only with `deleted`); 158 when there is none.

    `for_update` holds its row to the end of the transaction, read as another that held it
    left it: two that take a program away (a delete, a rename) do so one after the other.
    """
    query = select(LibraryProgram).where(LibraryProgram.folder == check_folder(folder),
                                         LibraryProgram.name == check_program_name(name))
    program = session.scalar(db.held(session, query) if for_update else query)
    if program is None:
        raise _missing(f"no program {folder}/{name} in the library")
    if program.deleted and not deleted:  # its versions are kept: say how to have it back
        raise _missing(f"{program.path} was deleted from the library; "
                       f"dncq library restore {program.path} VERSION brings it back")
    return program


def holds(*, session: Session, folder: str, name: str) -> bool:
    """Whether the library holds the program `folder/name`, not deleted (a name it could not
    hold is not held)."""
    try:
        find(session=session, folder=folder, name=name)
    except ContractError:
        return False
    return True


def spelled(*, session: Session, folder: str, name: str) -> tuple[str, str]:
    """`folder/name` as the library spells it: as given when a program is there so, else
    the one program there in another case (`Vipros/Bracket.nc` for `VIPROS/BRACKET.NC`); as
    given when there is none, or several."""
    found = _spellings(session, folder, name)
    return found.pop() if len(found) == 1 else (folder, name)


def spelled_folder(*, session: Session, folder: str) -> str:
    """`folder` as the library spells it (see `spelled`)."""
    found = {f for f, _ in _spellings(session, folder, None)}
    return found.pop() if len(found) == 1 else folder


def _spellings(session: Session, folder: str, name: str | None) -> set[tuple[str, str]]:
    """The (folder, name) of the programs at `folder` (and `name`): those spelled as given,
    if any, else those that are in another case."""
    as_given = [LibraryProgram.folder == folder]
    any_case = [func.lower(LibraryProgram.folder) == folder.lower()]
    if name is not None:
        as_given.append(LibraryProgram.name == name)
        any_case.append(func.lower(LibraryProgram.name) == name.lower())
    for where in (as_given, any_case):
        found = session.execute(select(LibraryProgram.folder, LibraryProgram.name).where(
            LibraryProgram.deleted.is_(False), *where).distinct()).all()
        if found:
            return {(f, n) for f, n in found}
    return set()


def current(program: LibraryProgram) -> LibraryVersion | None:
    """The program's highest-numbered version, whatever its state."""
    return program.versions[-1] if program.versions else None


def approved(program: LibraryProgram) -> LibraryVersion | None:
    """The program's current approved version: what rollouts and listings use."""
    return next((v for v in reversed(program.versions)
                 if v.state is VersionState.APPROVED), None)


def waiting_after(program: LibraryProgram, chosen: LibraryVersion) -> list[LibraryVersion]:
    """The program's versions after `chosen` still waiting for a decision, oldest first."""
    return [v for v in program.versions
            if v.number > chosen.number and v.state is VersionState.PENDING]


def version(*, session: Session, folder: str, name: str, number: int,
            deleted: bool = True) -> LibraryVersion:
    """Version `number` of `folder/name`; 158 when there is none."""
    program = find(session=session, folder=folder, name=name, deleted=deleted)
    found = next((v for v in program.versions if v.number == number), None)
    if found is None:
        raise _missing(f"{program.path} has no version {number}")
    return found


ADD_TRIES = 3  # a new program made by several at once: the ones that lose read it again


def add(*, session: Session, folder: str, name: str, blob: blobs.BlobInfo, note: str = "",
        created_by: str = "api", source: str = "upload", approve: bool = False) -> Added:
    """Add stored bytes as a program, or as its next version; its current bytes add none,
    and no bytes at all are refused (20001).

    Adds of one program at once all land, numbered one after the other: each holds the
    program's row in turn, and one that finds the new program's row made by another,
    committed meanwhile, reads again and adds to it.
    """
    check_folder(folder)
    check_program_name(name)
    check_size(folder=folder, name=name, size_bytes=blob.size)
    db.write_first(session)  # the savepoint below reads before it writes
    for attempt in range(ADD_TRIES):
        try:
            with session.begin_nested():
                return _add_once(session=session, folder=folder, name=name, blob=blob,
                                 note=note, created_by=created_by, source=source,
                                 approve=approve)
        except IntegrityError:
            session.expire_all()
            if attempt == ADD_TRIES - 1:
                raise ContractError(ErrorCode.PATH_EXISTS, f"{folder}/{name} is being changed "
                                    "by others at this moment; try again") from None
    raise AssertionError("unreachable")


def hold_name(*, session: Session, folder: str, name: str) -> None:
    """Hold `folder/name` for a program this transaction is to add under it (a rename's new
    name); 142 when a program is there, also one another transaction added and held
    meanwhile (`add` would have made it a version of that one)."""
    taken = ContractError(ErrorCode.PATH_EXISTS, f"EXISTS: {folder}/{name}")
    existing = session.scalar(db.held(session, select(LibraryProgram).where(
        LibraryProgram.folder == check_folder(folder),
        LibraryProgram.name == check_program_name(name))))
    if existing is not None:
        if not existing.deleted:
            raise taken
        return  # a deleted one's row, held: its history goes on under the new program
    try:
        with session.begin_nested():
            session.add(LibraryProgram(folder=folder, name=name))
    except IntegrityError:  # inserted by another, which committed meanwhile
        raise taken from None


def check_size(*, folder: str, name: str, size_bytes: int) -> None:
    """20001 for a program of no bytes: approved, a rollout would send the machine nothing.
    An upload asks before its bytes are kept, so that a refused one leaves no blob."""
    if size_bytes == 0:
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            f"{folder}/{name}: an empty program is no program; nothing added")


def _add_once(*, session: Session, folder: str, name: str, blob: blobs.BlobInfo, note: str,
              created_by: str, source: str, approve: bool) -> Added:
    # Held, and read as another that held it left it: a version added while another request
    # deletes the program brings it back rather than landing under the deleted one, and
    # adds of one program number one after the other.
    program = session.scalar(db.held(session, select(LibraryProgram).where(
        LibraryProgram.folder == folder, LibraryProgram.name == name)
        .options(selectinload(LibraryProgram.versions))))
    if program is None:
        program = LibraryProgram(folder=folder, name=name)
        session.add(program)
    restored = bool(program.deleted)  # a new one's column default comes at its insert
    if restored:  # added again: the same program, its history goes on
        program.deleted, program.deleted_at = False, None
    latest = current(program)
    if latest is not None and latest.sha256 == blob.sha256:
        if approve and latest.state is not VersionState.APPROVED:
            _decide(latest, VersionState.APPROVED, created_by)
        session.flush()
        return Added(latest, created=False, restored=restored)
    new = LibraryVersion(number=latest.number + 1 if latest else 1, sha256=blob.sha256,
                         size=blob.size, note=note, source=source, created_by=created_by,
                         created_at=utcnow(), state=VersionState.PENDING)
    program.versions.append(new)
    if approve:
        _decide(new, VersionState.APPROVED, created_by)
    session.flush()
    return Added(new, created=True, restored=restored)


def list_programs(*, session: Session, folder: str | None = None,
                  deleted: bool = False) -> list[LibraryProgram]:
    """Programs by folder and name: of `folder` and the folders below it, or all."""
    query = select(LibraryProgram).options(selectinload(LibraryProgram.versions))
    if folder is not None:
        check_folder(folder)
        query = query.where(or_(LibraryProgram.folder == folder,
                                LibraryProgram.folder.startswith(folder + "/",
                                                                 autoescape=True)))
    if not deleted:
        query = query.where(LibraryProgram.deleted.is_(False))
    return list(session.scalars(query.order_by(LibraryProgram.folder, LibraryProgram.name)))


def history(*, session: Session, folder: str, name: str) -> list[LibraryVersion]:
    """Every version of the program, newest first; a deleted program's too."""
    return list(reversed(find(session=session, folder=folder, name=name,
                              deleted=True).versions))


def diff(*, session: Session, settings: Settings, folder: str, name: str, old: int, new: int,
         context_lines: int = 3) -> str:
    """A unified diff of the text of two versions (UTF-8, else Latin-1)."""
    sides = [version(session=session, folder=folder, name=name, number=n) for n in (old, new)]
    for side in sides:
        if side.size > DIFF_MAX_BYTES:
            raise ContractError(ErrorCode.FILE_TOO_LARGE,
                                f"v{side.number} is over {DIFF_MAX_BYTES} bytes: no diff")
    before, after = (text_lines(blobs.read_all(settings, s.sha256)) for s in sides)
    path = sides[0].program.path
    return ended(difflib.unified_diff(before, after, fromfile=f"{path} v{old}",
                                      tofile=f"{path} v{new}", n=context_lines))


def text_lines(data: bytes) -> list[str]:
    """A program's lines as a diff compares them (UTF-8, else Latin-1), ends kept."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")  # every byte is a character: a diff is never refused
    return text.splitlines(keepends=True)


def ended(lines: Iterator[str]) -> str:
    """A diff's lines as one text, each ended."""
    # a last line without its newline would run into the next one
    return "".join(line if line.endswith(("\n", "\r")) else line + "\n" for line in lines)


def restore(*, session: Session, folder: str, name: str, number: int,
            created_by: str = "api", approve: bool = False) -> Added:
    """A new version with the bytes of version `number`, noted `restore of vN`."""
    old = version(session=session, folder=folder, name=name, number=number)
    what = f"restore of v{number}"
    return add(session=session, folder=folder, name=name,
               blob=blobs.BlobInfo(old.sha256, old.size), note=what, source=what,
               created_by=created_by, approve=approve)


def delete(*, session: Session, folder: str, name: str) -> LibraryProgram:
    """Take the program out of the library; its versions stay (adding it again goes on).

    Of two that take one program away at once (a delete, a rename), the second is told 158.
    """
    program = find(session=session, folder=folder, name=name, for_update=True)
    program.deleted, program.deleted_at = True, utcnow()
    session.flush()
    return program


class DecidedMeanwhile(ContractError):
    """The version was decided the other way since it was read: the decision is not made
    (20409, not a bad parameter: the same request was right when it was read)."""

    def __init__(self, status_msg: str) -> None:
        super().__init__(ErrorCode.DECIDED_ALREADY, status_msg)


def decide(*, session: Session, folder: str, name: str, number: int | None,
           state: VersionState, decided_by: str = "api") -> LibraryVersion:
    """Approve or reject a version (default: the current one), deciding again one decided
    before as asked; DecidedMeanwhile when another decided it the other way since it was
    read, and the other's decision, answered as made, when it was the same one."""
    if state is VersionState.PENDING:
        raise ContractError(ErrorCode.BAD_PARAMETER, "a version is approved or rejected")
    program = find(session=session, folder=folder, name=name)
    chosen = (current(program) if number is None else
              version(session=session, folder=folder, name=name, number=number))
    if chosen is None:
        raise _missing(f"{program.path} has no version")
    # Every column of the decision in one statement, made only on the state it was read
    # in: of two decisions at once, one is made and the other told, where the last won.
    made = db.rowcount(session.execute(
        update(LibraryVersion)
        .where(LibraryVersion.id == chosen.id, LibraryVersion.state == chosen.state)
        .values(state=state, decided_by=decided_by, decided_at=utcnow())
        .execution_options(synchronize_session=False)))
    session.refresh(chosen)
    if not made and chosen.state is not state:
        raise DecidedMeanwhile(f"{program.path} v{chosen.number} was {chosen.state.value} "
                               f"meanwhile by {chosen.decided_by}; it was not "
                               f"{state.value}")
    return chosen


def _decide(chosen: LibraryVersion, state: VersionState, decided_by: str) -> None:
    chosen.state, chosen.decided_by, chosen.decided_at = state, decided_by, utcnow()


def for_send(*, session: Session, folder: str, name: str,
             number: int | None) -> LibraryVersion:
    """The version a send rolls out: the current approved one, or any one asked by number."""
    program = find(session=session, folder=folder, name=name)
    if number is not None:
        return version(session=session, folder=folder, name=name, number=number)
    chosen = approved(program)
    if chosen is None:
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            f"{program.path} has no approved version; approve one or give "
                            "its number")
    return chosen


def assign(*, session: Session, folder: str, machine_ids: list[str]) -> list[LibraryAssignment]:
    """Give machines the programs of `folder` (already given ones stay as they are); 10003
    for ids no machine has, and none is given it."""
    check_folder(folder)
    wanted = list(dict.fromkeys(machine_ids))
    registered = registry.of_ids(session=session, machine_ids=wanted)
    if missing := [machine_id for machine_id in wanted if machine_id not in registered]:
        hints = registry.hints(session=session, names=missing)
        raise ContractError(ErrorCode.MACHINE_NOT_FOUND, "no machine " + ", ".join(
            m + hints.get(m, "") for m in missing) + f"; {folder} was given to none")
    if wanted:  # two admins giving one folder at the same moment: the second adds nothing
        now = utcnow()
        session.execute(db.upsert_of(session)(LibraryAssignment).on_conflict_do_nothing(), [
            {"machine_id": machine_id, "folder": folder, "created_at": now}
            for machine_id in wanted])
    given: dict[str, LibraryAssignment] = {}
    for chunk in db.in_chunks(wanted):  # a fleet of 100,000 given one folder
        given.update((row.machine_id, row) for row in session.scalars(select(
            LibraryAssignment).where(LibraryAssignment.folder == folder,
                                     LibraryAssignment.machine_id.in_(chunk))))
    return [given[machine_id] for machine_id in wanted]


def unassign(*, session: Session, folder: str, machine_ids: list[str]) -> int:
    """Take `folder` from machines; returns how many had it."""
    check_folder(folder)
    rows = [r for m in dict.fromkeys(machine_ids)
            if (r := session.get(LibraryAssignment, (m, folder))) is not None]
    for row in rows:
        session.delete(row)
    session.flush()
    return len(rows)


def assignments(*, session: Session, machine_id: str | None = None,
                folder: str | None = None) -> list[LibraryAssignment]:
    """Which machines take which folders, by machine and folder."""
    query = select(LibraryAssignment)
    if machine_id is not None:
        query = query.where(LibraryAssignment.machine_id == machine_id)
    if folder is not None:
        query = query.where(LibraryAssignment.folder == folder)
    return list(session.scalars(query.order_by(LibraryAssignment.machine_id,
                                               LibraryAssignment.folder)))


def machine_programs(*, session: Session,
                     machine_id: str) -> list[tuple[LibraryProgram, LibraryVersion]]:
    """A machine's library programs: the current approved version of each program of its
    assigned folders (exactly those folders, not below), by folder and name."""
    folders = [a.folder for a in assignments(session=session, machine_id=machine_id)]
    if not folders:
        return []
    query = (select(LibraryProgram).options(selectinload(LibraryProgram.versions))
             .where(LibraryProgram.folder.in_(folders), LibraryProgram.deleted.is_(False))
             .order_by(LibraryProgram.folder, LibraryProgram.name))
    return [(p, v) for p in session.scalars(query) if (v := approved(p)) is not None]
