"""The inbox's operations: receive, list, show, diff, approve, reject, prune.

A program a machine sends that is not a request is received here, never into the library:
its bytes become a blob (jobs.library.blobs) and it waits as a pending item. Only `approve`
makes it a library version, a new one beside those before it; the approved program a
machine is given does not change until someone approves. Failed receptions are kept too,
as failed items, the newest `inbox_failed_keep` per machine; rejected ones until
`inbox_rejected_keep_days` after the decision.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path

from sqlalchemy import delete, event, select, update
from sqlalchemy.orm import Session

from jobs.db import rowcount
from jobs.errors import ContractError, ErrorCode
from jobs.inbox.describe import describe
from jobs.inbox.models import InboxItem, InboxState
from jobs.library import blobs
from jobs.library import service as library
from jobs.library.models import LibraryVersion
from jobs.library.names import check_folder, check_program_name
from jobs.models import Run, utc_text, utcnow
from jobs.settings import Settings

MAX_NAME_CHARS = 255  # inbox_items.name
MAX_LIST = 1000  # items one listing answers
DECIDABLE = (InboxState.PENDING, InboxState.REJECTED)  # a rejected item may be approved later


class Undecidable(ContractError):
    """The item's state does not allow the decision: decided already (20409), by another
    meanwhile or before, or a failed reception (20001)."""

    def __init__(self, status_msg: str, code: ErrorCode = ErrorCode.DECIDED_ALREADY) -> None:
        super().__init__(code, status_msg)


def receive(*, session: Session, settings: Settings, machine_id: str, data: bytes,
            name: str | None, folder: str, job_id: str | None = None) -> InboxItem:
    """Keep a program a machine sent as a pending item; the library is not touched."""
    return _keep(session=session, settings=settings, machine_id=machine_id, data=data,
                 name=name, folder=folder, job_id=job_id, state=InboxState.PENDING, reason="")


def receive_failed(*, session: Session, settings: Settings, machine_id: str, data: bytes,
                   reason: str, job_id: str | None = None, name: str | None = None,
                   folder: str = "") -> InboxItem:
    """Keep a failed reception (what arrived, and why it failed) as a failed item; only the
    newest `inbox_failed_keep` of the machine's failed items stay."""
    item = _keep(session=session, settings=settings, machine_id=machine_id, data=data,
                 name=name, folder=folder, job_id=job_id, state=InboxState.FAILED,
                 reason=reason)
    older = list(session.scalars(
        select(InboxItem).where(InboxItem.machine_id == machine_id,
                                InboxItem.state == InboxState.FAILED)
        .order_by(InboxItem.received_at.desc(), InboxItem.id.desc())
        .offset(settings.inbox_failed_keep)))
    _remove(session=session, settings=settings, items=older)
    return item


def _keep(*, session: Session, settings: Settings, machine_id: str, data: bytes,
          name: str | None, folder: str, job_id: str | None, state: InboxState,
          reason: str) -> InboxItem:
    prune(session=session, settings=settings)  # each reception keeps the retention
    blob = blobs.put(settings, [data])
    said = describe(data)
    received_at = utcnow()
    # A name the library would refuse is kept as it came: the bytes are never lost for it,
    # and approve says what is wrong (and takes another name).
    chosen = name or said.program_number or f"RECEIVED-{received_at:%Y%m%d-%H%M%S}"
    item = InboxItem(machine_id=machine_id, received_at=received_at,
                     name=chosen[:MAX_NAME_CHARS], program_number=said.program_number,
                     comment=said.comment, folder=folder, sha256=blob.sha256, size=blob.size,
                     state=state, reason=reason, job_id=job_id)
    session.add(item)
    session.flush()
    return item


def list_items(*, session: Session, machine_id: str | None = None,
               state: InboxState | None = None, limit: int = 100) -> list[InboxItem]:
    """Items newest first, of one machine or all, in one state or any."""
    query = select(InboxItem)
    if machine_id is not None:
        query = query.where(InboxItem.machine_id == machine_id)
    if state is not None:
        query = query.where(InboxItem.state == state)
    query = query.order_by(InboxItem.received_at.desc(), InboxItem.id.desc())
    return list(session.scalars(query.limit(max(1, min(limit, MAX_LIST)))))


def get(*, session: Session, item_id: int) -> InboxItem:
    """The item `item_id`; 158 when there is none."""
    item = session.get(InboxItem, item_id)
    if item is None:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no inbox item {item_id}")
    return item


def approved_copy(*, session: Session, item: InboxItem) -> LibraryVersion | None:
    """The library's current approved version of the item's folder/name, if there is one."""
    try:
        program = library.find(session=session, folder=item.folder, name=item.name)
    except ContractError:  # none, deleted, or a name the library would refuse
        return None
    return library.approved(program)


def diff(*, session: Session, settings: Settings, item_id: int,
         context_lines: int = 3) -> str:
    """A unified diff from the approved copy of the item's folder/name to the item; when
    there is none, or the bytes are the same, a line that says so."""
    item = get(session=session, item_id=item_id)
    copy = approved_copy(session=session, item=item)
    if copy is None:
        return f"no approved copy of {item.path} in the library\n"
    if copy.sha256 == item.sha256:
        return f"the same bytes as the approved {item.path} v{copy.number}\n"
    for what, size in ((f"{item.path} v{copy.number}", copy.size),
                       (f"inbox item {item.id}", item.size)):
        if size > library.DIFF_MAX_BYTES:
            raise ContractError(ErrorCode.FILE_TOO_LARGE,
                                f"{what} is over {library.DIFF_MAX_BYTES} bytes: no diff")
    before, after = (library.text_lines(blobs.read_all(settings, digest))
                     for digest in (copy.sha256, item.sha256))
    return library.ended(difflib.unified_diff(
        before, after, fromfile=f"{item.path} v{copy.number} (approved)",
        tofile=f"inbox {item.id} from {item.machine_id} at {utc_text(item.received_at)}",
        n=context_lines))


def approve(*, session: Session, settings: Settings, item_id: int, folder: str | None = None,
            name: str | None = None, decided_by: str, note: str = "") -> LibraryVersion:
    """Make the item a new approved version of its folder/name (or of `folder`/`name`);
    the versions before it stay."""
    item = get(session=session, item_id=item_id)
    _check_decidable(item, "approved")
    folder, name = check_folder(folder or item.folder), check_program_name(name or item.name)
    if not blobs.exists(settings, item.sha256):
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"inbox item {item.id}'s content is gone")
    _claim(session=session, item=item, state=InboxState.APPROVED, decided_by=decided_by)
    added = library.add(session=session, folder=folder, name=name,
                        blob=blobs.BlobInfo(item.sha256, item.size),
                        note=note or item.comment or "", created_by=decided_by,
                        source=f"inbox {item.id} from {item.machine_id}"[:200], approve=True)
    item.folder, item.name, item.library_version = folder, name, added.version.number
    session.flush()
    return added.version


def reject(*, session: Session, item_id: int, decided_by: str, reason: str = "") -> InboxItem:
    """Refuse a pending item; it is kept until pruned `inbox_rejected_keep_days` later."""
    item = get(session=session, item_id=item_id)
    if item.state is InboxState.REJECTED:
        raise Undecidable(f"inbox item {item.id} is rejected already")
    _check_decidable(item, "rejected")
    _claim(session=session, item=item, state=InboxState.REJECTED, decided_by=decided_by)
    item.reason = reason
    session.flush()
    return item


def _check_decidable(item: InboxItem, what: str) -> None:
    if item.state is InboxState.APPROVED:
        raise Undecidable(f"inbox item {item.id} is approved already, as {item.path} "
                          f"v{item.library_version}")
    if item.state is InboxState.FAILED:
        why = item.reason or "no reason given"
        raise Undecidable(f"inbox item {item.id} is a failed reception ({why}); "
                          f"it cannot be {what}", ErrorCode.BAD_PARAMETER)


def _claim(*, session: Session, item: InboxItem, state: InboxState, decided_by: str) -> None:
    """Move the item to `state` if it is still in the state it was read in: of two
    decisions at once, one wins and the other is told what happened."""
    was = item.state
    claimed = rowcount(session.execute(
        update(InboxItem).where(InboxItem.id == item.id, InboxItem.state == was)
        .values(state=state, decided_by=decided_by, decided_at=utcnow())
        .execution_options(synchronize_session=False)))
    session.refresh(item)
    if not claimed:
        _check_decidable(item, state.value)
        raise Undecidable(f"inbox item {item.id} was {item.state.value} meanwhile")


def prune(*, session: Session, settings: Settings) -> int:
    """Remove items rejected more than `inbox_rejected_keep_days` ago, and the content
    nothing else uses; returns how many went."""
    cutoff = utcnow() - timedelta(days=settings.inbox_rejected_keep_days)
    # One statement that checks as it deletes: an item approved since it was rejected stays
    gone = list(session.scalars(delete(InboxItem).where(
        InboxItem.state == InboxState.REJECTED, InboxItem.decided_at < cutoff)
        .returning(InboxItem.sha256)))
    # with the content spared an hour ago by earlier removals, no longer written or reused
    spared = blobs.spared(settings)
    _remove_unused(session=session, settings=settings, digests=set(gone) | spared,
                   looked_again=spared)
    return len(gone)


def _remove(*, session: Session, settings: Settings, items: list[InboxItem]) -> None:
    """Delete items; their blobs that nothing else uses go once the deletion is committed."""
    for item in items:
        session.delete(item)
    session.flush()
    _remove_unused(session=session, settings=settings, digests={item.sha256 for item in items})


def _remove_unused(*, session: Session, settings: Settings, digests: set[str],
                   looked_again: frozenset[str] = frozenset()) -> None:
    """Remove the blobs of `digests` that nothing else uses once the session commits, but
    for one an upload wrote or reused lately (blobs.remove_unused); then forget that the
    `looked_again` ones were spared (blobs.spared)."""
    if not digests:
        return
    used = set(session.scalars(select(InboxItem.sha256).where(InboxItem.sha256.in_(digests))))
    used.update(session.scalars(select(LibraryVersion.sha256)
                                .where(LibraryVersion.sha256.in_(digests))))
    used.update(session.scalars(select(Run.program_id).where(Run.program_id.in_(digests))))
    # A drip-feed program uploaded with these bytes has a record beside the blob
    # (jobs.dnc.programs.program_dir) and no row: its record keeps the blob.
    used.update(d for d in digests if (settings.data_dir / "programs" / f"{d}.json").exists())
    _unlink_after_commit(session, [blobs.path(settings, d) for d in digests - used],
                         lambda: blobs.forget_spared(settings, looked_again))


_UNLINK = "inbox_blobs_to_unlink"  # session.info key: what to do once committed


def _unlink_after_commit(session: Session, files: list[Path],
                         first: Callable[[], None]) -> None:
    """Remove `files` when the session commits, after `first()`; a rollback keeps them (its
    rows stay)."""
    if _UNLINK not in session.info:
        session.info[_UNLINK] = []
        event.listen(session, "after_commit", _unlink_pending)
        event.listen(session, "after_rollback", _forget_pending)
    session.info[_UNLINK].append((first, files))


def _unlink_pending(session: Session) -> None:
    pending, session.info[_UNLINK] = session.info[_UNLINK], []
    for first, files in pending:
        first()  # a blob removed below and spared again is marked again
        for file in files:
            blobs.remove_unused(file)


def _forget_pending(session: Session) -> None:
    session.info[_UNLINK] = []
