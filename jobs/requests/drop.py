"""Requests by file drop: what a control writes into a folder of its machine, handled.

On a machine reached through a folder (ftp, share, mock, gateway) the control writes a
request program (or any program, to be received) into the machine's `drop_folder`. Every
worker's reaper looks into the drop folders every `request_scan_interval_s`, each machine
under its lease (a busy machine waits for the next look). Each file is handled like a
program sent over a link, under a job id made from the file (jobs.requests.dropped: a file
handled by a worker lost before it removed it is only removed), then removed, its removal
noted as under way until its job is marked (one a worker lost in between began is marked by
the next whole look that no longer finds the file); the answers
are written into `answer_folder` (by default the drop folder), replacing dncq's own older
answer of the same name (never a file it did not write; a report of the same look is added
to, not replaced), and remembered, so that a later look does not take them for programs
the control sent.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path

from jobs.db import session_scope
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import door, registry
from jobs.fleet.registry import MachineSpec
from jobs.fleet.rules import MachineFiles
from jobs.folders import private_dir
from jobs.requests import dropped, handling
from jobs.requests.answers import report_program
from jobs.run import leases
from jobs.run.slot import hand_on
from jobs.settings import Settings
from worker import transports

log = logging.getLogger(__name__)

MAX_DROPPED_BYTES = 16 * 1024 * 1024  # a dropped file is read whole
DROP_LOOK_GROUP = "requests:drop-look"
SETTLE_S = 2.0  # a file changed more recently than this may be half written


def candidates(settings: Settings) -> list[MachineSpec]:
    """Machines whose operators drop requests into a folder."""
    with session_scope(settings.resolved_database_url) as session:
        specs = registry.taking_requests(session=session)
    found = []
    for spec in specs:
        if not spec.enabled or not spec.requests or spec.transport not in transports.REGISTRY:
            continue
        try:
            rs = spec.request_settings()
        except ValueError:
            continue  # refused at import; a row changed behind the registry's back
        if rs.enabled and rs.drop_folder:
            found.append(spec)
    return found


def scan(*, settings: Settings) -> int:
    """Look into every drop folder once; returns how many files were handled."""
    handled = 0
    for spec in candidates(settings):
        try:
            handled += scan_machine(settings=settings, spec=spec)
        except Exception:  # one machine's trouble must not keep the others' requests waiting
            log.exception("looking into the drop folder of machine %s failed", spec.id)
    return handled


def scan_machine(*, settings: Settings, spec: MachineSpec) -> int:
    """Handle what the machine's drop folder holds, under its lease; 0 when it is busy."""
    url = settings.resolved_database_url
    # One group for every look at the machine, which holds one slot of it at most: a second
    # look beside the first could read a file the first is removing, and take it for a new
    # one once the first had marked its job. Its other slots stay for other operations.
    holder = leases.acquire(url, machine_id=spec.id, max_concurrent=spec.max_concurrent,
                            group=DROP_LOOK_GROUP, ttl_s=settings.lease_ttl_s)
    if holder is None:
        return 0
    handled = 0
    try:
        with leases.Heartbeat(url, holder=holder, ttl_s=settings.lease_ttl_s):
            files = door.open_files(spec, data_dir=settings.data_dir)
            try:
                handled = _scan(settings, spec, files)
            finally:
                files.close()
    finally:
        leases.release(url, holder=holder)
        hand_on(settings, [spec.id])
    return handled


def _scan(settings: Settings, spec: MachineSpec, files: MachineFiles) -> int:
    rs = spec.request_settings()
    drop = rs.drop_folder or ""
    answers = DropAnswerer(settings, spec, files, rs.answer_folder or drop)
    # Answers kept in a folder of their own are never in the drop folder: a file there with
    # an answer's bytes is the control sending that program back.
    answers_here = files.paths.resolve(answers.folder, None) == files.paths.resolve(drop, None)
    handled = 0
    begun_before = dropped.under_way(settings=settings, machine_id=spec.id)  # by lost workers
    for name in files.list_program_dir(drop, None)["programs"]:
        try:
            ref = files.ref(name, drop, None)
        except ContractError as exc:  # a name dncq cannot take (a backslash, a control
            _unusable_name(settings, spec, name, exc)  # character): the others go on
            continue
        entry = files.stat(ref)
        if _being_written(entry.mtime):
            continue  # the control may still be writing it: the next look takes it
        data: bytes | None
        try:
            data = files.read_bytes(ref, max_bytes=MAX_DROPPED_BYTES)
        except ContractError as exc:
            if exc.code is not ErrorCode.FILE_TOO_LARGE:
                raise
            data = None
        if data is not None and answers_here and answers.is_ours(name, data):
            continue  # an answer the control has not taken yet
        origin = f"drop:{name}"
        job = dropped.job_for(settings=settings, machine_id=spec.id,
                              path=files.display_path(ref),
                              size=entry.size if data is None else len(data),
                              mtime=entry.mtime, data=data or b"")
        if job.recorded:
            log.info("machine %s: %s was handled as job %s by a worker lost before it "
                     "removed the file; removed, not handled again", spec.id, name, job.id)
        elif data is None:
            handling.receive_failed(settings=settings, spec=spec, text=b"",
                                    reason=f"{name} is over {MAX_DROPPED_BYTES} bytes, more "
                                           "than a program dropped for dncq may be",
                                    origin=origin, job_id=job.id)
        else:
            handling.handle(settings=settings, spec=spec, text=data, answerer=answers,
                            origin=origin, job_id=job.id)
        dropped.removing(settings=settings, machine_id=spec.id, job_id=job.id)
        files.delete(ref)
        dropped.removed(settings=settings, machine_id=spec.id, job_id=job.id)
        handled += 1
    # A removal begun before this look whose file the whole look did not find was done.
    dropped.gone(settings=settings, machine_id=spec.id,
                 job_ids=begun_before & dropped.under_way(settings=settings, machine_id=spec.id))
    return handled


_UNUSABLE_SAID: set[tuple[str, str]] = set()  # (machine, name) told once per process


def _unusable_name(settings: Settings, spec: MachineSpec, name: str,
                   exc: ContractError) -> None:
    """Say once that a dropped file cannot be taken: a failed reception in the inbox and a
    warning. It stays in the folder for someone at the machine to rename or remove; until
    then every look passes it by, and takes the files after it."""
    if (spec.id, name) in _UNUSABLE_SAID:
        return
    _UNUSABLE_SAID.add((spec.id, name))
    why = f"the file {name!r} in the drop folder cannot be taken: {exc.status_msg or exc}; " \
          "rename or remove it at the machine"
    handling.receive_failed(settings=settings, spec=spec, text=b"", reason=why,
                            origin=f"drop:{name!r}")


def _being_written(mtime: float | None) -> bool:
    """Whether a file of that modification time changed in the last `SETTLE_S`; a time
    ahead of ours (the machine's clock is off) or none at all says nothing, and it is taken."""
    return mtime is not None and 0 <= time.time() - mtime < SETTLE_S


class DropAnswerer:
    """Answers written as files into the answer folder, and remembered as dncq's own; one
    look's reports of the same name written as one (the control has not taken the first)."""

    def __init__(self, settings: Settings, spec: MachineSpec, files: MachineFiles,
                 folder: str) -> None:
        self.files, self.folder = files, folder
        self.rs = spec.request_settings()
        self._book = private_dir(settings.data_dir / "requests") / f"{spec.id}.answers.json"
        self._reports: dict[str, list[str]] = {}  # the lines of each report written so far

    def deliver(self, name: str, data: bytes, report: list[str] | None = None) -> None:
        """Write the answer `name`, over dncq's own earlier answer of that name only; a
        report over one of this look's reports holds the lines of both.

        Raises:
            ContractError: 142 when a file dncq did not write has that name (a program the
                control sent, not taken yet, or one edited there): it is never replaced.
        """
        if report is not None:
            report = self._reports.get(name, []) + report
            data = report_program(report, self.rs)
        ref = self.files.ref(name, self.folder, None)
        there: bytes | None
        try:
            there = self.files.read_bytes(ref, max_bytes=MAX_DROPPED_BYTES)
        except ContractError as exc:
            if exc.code not in (ErrorCode.PATH_NOT_FOUND, ErrorCode.FILE_TOO_LARGE):
                raise
            there = None if exc.code is ErrorCode.PATH_NOT_FOUND else b""
        if there is not None:
            if not self.is_ours(name, there):
                raise ContractError(ErrorCode.PATH_EXISTS, (
                    f"{self.files.display_path(ref)} is a file dncq did not write; it is "
                    "not replaced by the answer: ask again once it is taken"))
            self.files.delete(ref, force=True)  # the control's previous answer of that name
        self.files.send_chunks(ref, iter([data]))
        book = self._read()
        book[name] = hashlib.sha256(data).hexdigest()
        temp = self._book.with_suffix(f".{os.getpid()}.tmp")
        temp.write_text(json.dumps(book))
        temp.replace(self._book)
        if report is not None:
            self._reports[name] = report
        else:  # a program of the report's name replaced it: the next report starts afresh
            self._reports.pop(name, None)

    def is_ours(self, name: str, data: bytes) -> bool:
        """Whether the file is an answer dncq wrote there, unchanged."""
        return self._read().get(name) == hashlib.sha256(data).hexdigest()

    def _read(self) -> dict[str, str]:
        try:
            loaded = json.loads(Path(self._book).read_text())
        except (FileNotFoundError, ValueError):
            return {}
        return loaded if isinstance(loaded, dict) else {}
