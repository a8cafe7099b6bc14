"""What one attempt of a target does on its open machine, by its job's kind.

A send writes the payload or a backup's file without overwriting, then replaces or
verifies as the job's options say; a delete, a backup's fetch and a drip-feed run each
come to an `Outcome`, which the runner records (worker.runner).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Generator
from dataclasses import dataclass

from sqlalchemy import select, update

from jobs import db, service
from jobs.backup import restore, store
from jobs.db import session_scope
from jobs.errors import ContractError, ErrorCode
from jobs.fleet.rules import FANUC_HEAD_BYTES, FileRef, MachineFiles
from jobs.models import JobKind, Payload, Target, TargetState
from jobs.run import running
from jobs.run.work import Work
from jobs.settings import Settings
from worker import drip_run
from worker.transports.base import CHUNK_BYTES

log = logging.getLogger(__name__)

PROGRESS_EVERY_S = 1.0  # how often a large transfer writes its progress


class Outcome:
    """What one attempt came to."""

    def __init__(self, *, error: ContractError | None = None,
                 state: TargetState = TargetState.SUCCEEDED, status_msg: str | None = None,
                 replaced_payload_id: str | None = None, behind: bool = False) -> None:
        self.error, self.state, self.status_msg = error, state, status_msg
        self.replaced_payload_id = replaced_payload_id
        self.behind = behind  # no attempt: the target waits behind another run, uncounted
        self.files: MachineFiles | None = None  # the open machine, kept for the next target


def execute(settings: Settings, files: MachineFiles, work: Work) -> Outcome:
    """One attempt of one target."""
    p = work.params
    if work.kind is JobKind.DNC_RUN:
        state, error, status_msg = drip_run.execute(settings, files, work)
        return Outcome(error=error, state=state, status_msg=status_msg)
    if work.kind is JobKind.BACKUP:
        count = store.fetch_target(settings, files, job_id=work.job.job_id,
                                   target_id=work.target_id, machine_id=work.machine_id,
                                   params=p)
        if files.left_out:  # in the backup's manifest too, which is partial
            return Outcome(status_msg=f"{count} files; left out ({len(files.left_out)}): "
                                      + ", ".join(x.path for x in files.left_out[:10]))
        return Outcome(status_msg=f"{count} file" if count == 1 else f"{count} files")
    if work.kind is JobKind.DELETE:
        ref = files.ref(p.get("fileName"), p.get("dirAtCNC"), p.get("subDir"))
        try:
            files.delete(ref, force=work.options.force)
        except ContractError as exc:
            if exc.code is ErrorCode.PATH_NOT_FOUND and work.previous_interrupted:
                return Outcome(status_msg="already deleted by the interrupted attempt")
            raise
        return Outcome()
    source = _source(settings, work)
    if source.listed_by == work.machine_id and not files.row.is_fanuc:
        # A file restored onto the machine that listed it goes back under its own name.
        ref = files.listed_ref(p["fileName"], p.get("dirAtCNC"), p.get("subDir"))
        return _send(settings, files, work, ref, source)
    head = source.head() if files.row.is_fanuc else b""  # Fanuc names it from its content
    ref = files.send_ref(p.get("fileName"), p.get("dirAtCNC"), p.get("subDir"), head)
    return _send(settings, files, work, ref, source)


class PayloadCache:
    """Payload bytes by id, kept in memory up to `max_bytes` (payloads never change)."""

    def __init__(self, max_bytes: int = 64 * 1024 * 1024) -> None:
        self.max_bytes = max_bytes
        self._items: OrderedDict[str, bytes] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, url: str, payload_id: str) -> bytes:
        with self._lock:
            if payload_id in self._items:
                self._items.move_to_end(payload_id)
                return self._items[payload_id]
        with session_scope(url) as session:
            payload = session.get(Payload, payload_id)
            if payload is None:
                raise ContractError(ErrorCode.INTERNAL_ERROR, f"payload {payload_id} is gone")
            data = payload.data
        with self._lock:
            self._items[payload_id] = data
            while sum(len(v) for v in self._items.values()) > self.max_bytes and self._items:
                self._items.popitem(last=False)
        return data


PAYLOADS = PayloadCache()


@dataclass(frozen=True)
class Source:
    """What a send target sends: its size and its bytes, as a fresh stream each time."""

    size: int
    chunks: Callable[[], Generator[bytes, None, None]]
    listed_by: str | None = None  # a restored file: the machine whose listing named it

    def head(self) -> bytes:
        """The first bytes, where a Fanuc program's name is."""
        with contextlib.closing(self.chunks()) as stream:
            return next(stream, b"")[:FANUC_HEAD_BYTES]


def _source(settings: Settings, work: Work) -> Source:
    """A restored file read from its backup, else the payload (kept in memory, like any
    request body, up to the body limits)."""
    if work.options.restore_from:
        zip_path, found = restore.find_member(settings=settings,
                                              backup_id=work.options.restore_from,
                                              archive_path=work.params["archivePath"])
        return Source(found.size, lambda: restore.read_member(zip_path, found),
                      listed_by=found.machine_id)
    assert work.payload_id is not None
    data = PAYLOADS.get(settings.resolved_database_url, work.payload_id)
    return Source(len(data), lambda: _in_chunks(data))


def _in_chunks(data: bytes) -> Generator[bytes, None, None]:
    """A payload in the transports' chunks, so that a large one reports its progress."""
    view = memoryview(data)
    for start in range(0, len(data), CHUNK_BYTES):
        yield bytes(view[start:start + CHUNK_BYTES])
    if not data:
        yield b""


def _send(settings: Settings, files: MachineFiles, work: Work, ref: FileRef,
          source: Source) -> Outcome:
    replaced: str | None = None
    try:
        try:
            _write(settings, files, work, ref, source)
        except ContractError as exc:
            if exc.code is not ErrorCode.PATH_NOT_FOUND or not work.options.make_dirs:
                raise
            files.ensure_dir(ref.place)
            _write(settings, files, work, ref, source)
    except ContractError as exc:
        if exc.code is not ErrorCode.PATH_EXISTS:
            raise
        if files.holds(ref, source.size, source.chunks()):  # sizes first, then in chunks
            if work.options.skip_identical:
                return Outcome(state=TargetState.SKIPPED, status_msg="identical file already there")
            if work.may_have_written:  # our own earlier attempt got the file there
                kept = _kept_by_an_earlier_attempt(settings, work)
                return Outcome(replaced_payload_id=kept, status_msg=(
                    _replaced_said(work) if kept else
                    "file already there from an earlier attempt"))
            if work.options.replace:  # keeping these bytes as "the old file" would lose it
                return Outcome(status_msg="the same file is already there; nothing replaced")
        if not work.options.replace:
            raise
        if not work.options.force:
            files.refuse_if_running(ref)
        replaced = _keep(settings, files, work, ref)
        try:
            files.delete(ref, force=True)
            _write(settings, files, work, ref, source)
        except ContractError as exc:  # the saved copy stays the target's, to restore
            return Outcome(error=exc, replaced_payload_id=replaced)
    if work.options.verify and not files.holds(ref, source.size, source.chunks()):
        raise ContractError(ErrorCode.VERIFY_MISMATCH, "the file read back differs")
    if replaced is None and work.options.replace:
        # An earlier attempt kept the file there and removed it, and was cut off before
        # writing: this one wrote into the gap, but the file was replaced all the same.
        replaced = _kept_by_an_earlier_attempt(settings, work)
    said = [_replaced_said(work)] if replaced else []
    if ref.name != work.params.get("fileName"):  # a Fanuc names it from its content
        said.append(f"stored as {files.display_path(ref)}")
    return Outcome(replaced_payload_id=replaced, status_msg="; ".join(said) or None)


def _replaced_said(work: Work) -> str:
    """What a target that replaced the file there says of it."""
    if work.kind is JobKind.RESTORE:  # the file it replaced is the newer one
        return "put back in place of the file there, which is kept with the job"
    return "replaced; the old file is kept with the job"


def _kept_by_an_earlier_attempt(settings: Settings, work: Work) -> str | None:
    """The copy an earlier attempt of the target kept of the file it was replacing (`_keep`
    records it before the delete), if any; a first attempt has none."""
    if work.attempt <= 1:
        return None
    with session_scope(settings.resolved_database_url) as session:
        return session.scalar(select(Target.replaced_payload_id)
                              .where(Target.id == work.target_id))


def _keep(settings: Settings, files: MachineFiles, work: Work, ref: FileRef) -> str:
    """Keep the file about to be replaced with the job, the target's before the file is
    deleted: a worker killed between the delete and the record of its result (or an
    unexpected error there) left the copy linked to nothing, and `restore-replaced` without
    it. Refused (and nothing replaced) when it is larger than the copies the database keeps,
    which are read into memory.

    A target keeps the first copy: the file a later attempt finds there may be what an
    earlier one wrote (read back wrong, or cut off), and `restore-replaced` must put back
    the file the job found, not its own."""
    earlier = _kept_by_an_earlier_attempt(settings, work)
    if earlier is not None:
        return earlier
    limit = settings.max_kept_file_bytes
    try:
        existing = files.read_bytes(ref, max_bytes=limit)
    except ContractError as exc:
        if exc.code is not ErrorCode.FILE_TOO_LARGE:
            raise
        raise ContractError(ErrorCode.FILE_TOO_LARGE,
                            f"the file there is over {limit} bytes, more than a replaced file "
                            "kept with its job may hold; delete it first") from None
    with session_scope(settings.resolved_database_url) as session:
        kept = service.store_payload(session=session, data=existing)
        session.execute(update(Target).where(Target.id == work.target_id)
                        .values(replaced_payload_id=kept))
        return kept


def _write(settings: Settings, files: MachineFiles, work: Work, ref: FileRef,
           source: Source) -> None:
    url = settings.resolved_database_url
    last = [0.0]

    def progress(done: int, _total: int | None) -> None:
        now = time.monotonic()
        if now - last[0] >= PROGRESS_EVERY_S:
            last[0] = now
            try:
                running.report_bytes(url=url, target_id=work.target_id, done=done,
                                     total=source.size)
            except Exception as exc:  # progress is a view: a lost database must not cut a transfer
                if not db.unreachable(exc):
                    raise
                log.warning("progress of target %s not recorded: %s", work.target_id,
                            type(exc).__name__)

    files.send_chunks(ref, source.chunks(),
                      progress=progress if source.size > 1 << 20 else None)
    if work.may_have_written:  # an attempt cut off before may have left its temporary file
        files.remove_parts_of(ref)
