"""One program a machine sent, handled: a request answered, anything else received.

A request becomes a `request` job with a target per action (jobs.requests.record); each
action is performed against the machine's program sources (jobs.requests.sources) and
gives a program to send back: the program asked for, a listing, a report of a delete or
rename, or an error program the operator can read. The answers go back in order through
an `Answerer` (the link, or the drop folder). A program that is no request goes to the
inbox for review (jobs.inbox), or is compared with the server's copy when a compare
request asked for that.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Protocol

from sqlalchemy.orm import Session

from jobs.db import session_scope
from jobs.dnc import restart
from jobs.errors import MESSAGES, ContractError, ErrorCode, from_transport
from jobs.fleet.registry import MachineSpec
from jobs.fleet.request_settings import Action, RequestSettings
from jobs.inbox import service as inbox
from jobs.library.line_ends import LINE_END
from jobs.models import TargetState
from jobs.requests import memory, record, sources
from jobs.requests.answers import (
    ReportKind,
    compare_lines,
    error_lines,
    listing_program,
    report_line,
    report_program,
)
from jobs.requests.plan import Plan, Step, plan
from jobs.settings import Settings
from worker.transports.base import TransportError
from worker.transports.optional import RequestLink
from worker.transports.serial_tape import program_name

log = logging.getLogger(__name__)

class Answerer(Protocol):
    """Where answers go: `deliver` sends one program, or raises the ContractError why not.
    `report`: the lines a report program was made of (None for any other answer)."""

    def deliver(self, name: str, data: bytes, report: list[str] | None = None) -> None: ...


class LinkAnswerer:
    """Answers on the machine's link: each once the operator switched the control to receive."""

    def __init__(self, link: RequestLink, rs: RequestSettings) -> None:
        self.link, self.rs = link, rs

    def deliver(self, name: str, data: bytes, report: list[str] | None = None) -> None:
        window = self.rs.switch_window_s
        try:
            if not self.link.wait_ready_to_read(timeout_s=window):
                raise ContractError(ErrorCode.MACHINE_TIMEOUT, f"the control was not switched "
                                    f"to receive within {window:g} s; ask again from the "
                                    f"control")
            if self.rs.request_delay_s:
                time.sleep(self.rs.request_delay_s)
            self.link.send_to_read(name, data)
        # A program punched instead (the listener takes it next) or a link lost: either
        # way this answer is not read in, and the request ends with why, not left running.
        except TransportError as exc:
            raise ContractError(from_transport(exc).code,
                                f"{exc}; ask again from the control") from exc


@dataclass
class _Answer:
    """What one target gives back, and its result."""

    target_id: int
    program: bytes | None
    # What the control and the drop folder get it as: the report's or the listing's name
    # from the settings (`DNCLIST.MPF`, `9998`), a sent program's own, else the file's.
    name: str = ""
    error: ContractError | None = None
    status_msg: str | None = None
    state: TargetState | None = None
    report: list[str] | None = None  # the lines of a report program


def _report(target_id: int, lines: list[str], rs: RequestSettings, *,
            error: ContractError | None = None, status_msg: str | None = None) -> _Answer:
    """A report program (`O8890`) as a target's answer."""
    return _Answer(target_id, report_program(lines, rs), rs.error_program.program_name,
                   error=error, status_msg=status_msg, report=lines)


def handle(*, settings: Settings, spec: MachineSpec, text: bytes, answerer: Answerer,
           origin: str, job_id: str | None = None, kept_s: float = 0.0) -> str:
    """Handle one program the machine sent; returns the id of the job that records it.

    Args:
        origin: how it came, for the record (`link`, `drop:<file>`).
        job_id: the id to record it under (the one it was kept under on the disk, or the
            one made from the dropped file).
        kept_s: how long ago it was read (a lost listener's program taken up late).
    """
    rs = spec.request_settings()
    planned = plan(text, rs)
    if planned.refused and not planned.is_request:  # not a program at all
        return _refused(settings, spec, text, planned.refused, origin, job_id)
    if planned.is_request and kept_s > rs.switch_window_s:
        # Nobody waits at the control for its answer any more, and a delete or a rename
        # carried out that late would surprise whoever works on the machine now.
        return _refused(settings, spec, text, stale_reason(kept_s, rs), origin, job_id)
    if not planned.is_request:
        return _received(settings, spec, rs, text, planned, answerer, origin, job_id)
    return _request(settings, spec, rs, text, planned, answerer, origin, job_id)


def stale_reason(kept_s: float, rs: RequestSettings) -> str:
    """Why a request read that long ago is not carried out."""
    return (f"a request read {kept_s / 60:.0f} min ago, while no worker could record it, is "
            f"not carried out later than switch_window_s ({rs.switch_window_s:g} s): "
            "ask again from the control")


def receive_failed(*, settings: Settings, spec: MachineSpec, text: bytes, reason: str,
                   origin: str, job_id: str | None = None) -> str:
    """A reception that broke off (no end mark, a link lost midway): kept as failed."""
    return _refused(settings, spec, text, reason, origin, job_id)


# -- what is not a request -------------------------------------------------------------


def _refused(settings: Settings, spec: MachineSpec, text: bytes, reason: str,
             origin: str, job_id: str | None) -> str:
    # The job, its failed item and its result in one transaction (as _received's).
    with session_scope(settings.resolved_database_url) as session:
        opened = record.add_job(session=session, settings=settings, machine_id=spec.id,
                                file_name=None, received=text, created_by=_by(spec, origin),
                                steps=[{"action": "receive", "origin": origin}], job_id=job_id)
        item = inbox.receive_failed(session=session, settings=settings, machine_id=spec.id,
                                    data=text, reason=reason, job_id=opened.job_id)
        record.finish_in(session=session, target_id=opened.target_ids[0],
                         error=ContractError(ErrorCode.BAD_PARAMETER, reason),
                         status_msg=f"kept as failed reception #{item.id}")
    log.warning("machine %s sent what dncq cannot take (%s)", spec.id, reason)
    return opened.job_id


def _received(settings: Settings, spec: MachineSpec, rs: RequestSettings, text: bytes,
              planned: Plan, answerer: Answerer, origin: str, job_id: str | None) -> str:
    compare = memory.take(settings, spec.id, "compare")
    if compare is not None:
        return _compare(settings, spec, rs, text, planned, compare, answerer, origin, job_id)
    directory = memory.get(settings, spec.id, "directory")
    folder = directory.folder if directory is not None else rs.receive_folder
    def job_in(session: Session) -> record.Opened:
        return record.add_job(session=session, settings=settings, machine_id=spec.id,
                              file_name=planned.received_name, received=text,
                              created_by=_by(spec, origin), job_id=job_id,
                              steps=[{"action": "receive", "folder": folder,
                                      "fileName": planned.received_name, "origin": origin}])

    # The job, its inbox item and its result in one transaction: a worker lost before the
    # commit leaves none of them, and the program, still in the drop folder or the spool,
    # is taken again; lost after it, the program is in the inbox and its job ended.
    try:
        with session_scope(settings.resolved_database_url) as session:
            opened = job_in(session)
            item = inbox.receive(session=session, settings=settings, machine_id=spec.id,
                                 data=text, name=planned.received_name, folder=folder,
                                 job_id=opened.job_id)
            record.finish_in(session=session, target_id=opened.target_ids[0],
                             status_msg=f"in the inbox as #{item.id} ({item.name}, for "
                                        f"{folder})")
    except ContractError as exc:  # not kept: the job says why
        with session_scope(settings.resolved_database_url) as session:
            opened = job_in(session)
            record.finish_in(session=session, target_id=opened.target_ids[0], error=exc)
    return opened.job_id


def _compare(settings: Settings, spec: MachineSpec, rs: RequestSettings, text: bytes,
             planned: Plan, compare: memory.Pending, answerer: Answerer, origin: str,
             job_id: str | None) -> str:
    name = compare.name or planned.received_name or ""
    opened = record.open_job(settings=settings, machine_id=spec.id, file_name=name,
                             received=text, created_by=_by(spec, origin),
                             steps=[{"action": "compare", "folder": compare.folder,
                                     "fileName": name, "origin": origin}], job_id=job_id)
    target_id = opened.target_ids[0]
    try:
        found = sources.find(settings, rs.parsed_sources, compare.folder, name,
                             held=spec.id)
        lines = compare_lines(_shown(compare.folder, name), found.data, text, rs)
        answer = _report(target_id, lines, rs, status_msg=(
            f"identical to {found.where}" if len(lines) == 1 else
            f"differs from {found.where}: {lines[0]}"))
    except ContractError as exc:
        answer = _error_answer(target_id, exc, _shown(compare.folder, name), rs)
    with _leases_kept(settings, opened.job_id):
        _deliver(settings, [answer], answerer, opened.job_id)
    return opened.job_id


# -- requests --------------------------------------------------------------------------


def _request(settings: Settings, spec: MachineSpec, rs: RequestSettings, text: bytes,
             planned: Plan, answerer: Answerer, origin: str, job_id: str | None) -> str:
    steps = list(planned.steps)
    for note in planned.log:
        log.info("machine %s request: %s", spec.id, note)
    views = [_view(s, origin) for s in steps] or [{"action": "none", "origin": origin}]
    if planned.log:  # skipped and unknown commands: in the record, with the first target
        views[0]["notes"] = list(planned.log)
    opened = record.open_job(settings=settings, machine_id=spec.id,
                             file_name=planned.program_name or planned.received_name,
                             received=text, created_by=_by(spec, origin), steps=views,
                             job_id=job_id)
    if planned.refused or not steps:  # the operator reads why on the control
        reason = planned.refused or "the request has no command dncq runs"
        answer = _report(opened.target_ids[0],
                         error_lines(report_line(ReportKind.REFUSED, rs, reason=reason)), rs,
                         error=ContractError(ErrorCode.BAD_PARAMETER, reason))
        with _leases_kept(settings, opened.job_id):
            _deliver(settings, [answer], answerer, opened.job_id)
        return opened.job_id
    with _leases_kept(settings, opened.job_id):
        answers = [_perform(settings, spec, rs, step, tid)
                   for step, tid in zip(steps, opened.target_ids, strict=True)]
        _deliver(settings, answers, answerer, opened.job_id)
    return opened.job_id


def _view(step: Step, origin: str) -> dict[str, Any]:
    view: dict[str, Any] = {"action": step.action.value, "folder": step.folder,
                            "origin": origin}
    if step.name:
        view["fileName"] = step.name
    if step.new_name:
        view["newName"] = step.new_name
    if step.restart_block:
        view["restartBlock"] = step.restart_block
    if step.note:
        view["asked"] = step.note
    return view


def _perform(settings: Settings, spec: MachineSpec, rs: RequestSettings, step: Step,
             target_id: int) -> _Answer:
    """Do one step; its answer program (an error program when it failed)."""
    srcs = rs.parsed_sources
    by = f"machine:{spec.id}"
    held = spec.id  # its lease is the listener's or the drop scan's, held while this runs
    shown = _shown(step.folder, step.name or "")
    try:
        if step.action is Action.SEND:
            found = sources.find(settings, srcs, step.folder, step.name or "", held=held)
            data = found.data
            name = program_name(data) or step.name or ""
            if step.restart_block:
                data = restarted(data, step.restart_block)
                return _Answer(target_id, data, name, status_msg=(
                    f"sent {found.where} restarted from {step.restart_block}"))
            return _Answer(target_id, data, name, status_msg=f"sent {found.where}")
        if step.action is Action.LIST:
            entries = sources.listing(settings, srcs, step.folder, held=held)
            return _Answer(target_id, listing_program(step.folder, entries, rs),
                           rs.listing.program_name,
                           status_msg=f"listed {len(entries)} programs of "
                                      f"{step.folder or 'the top folder'}")
        if step.action is Action.DELETE:
            where = sources.delete(settings, srcs, step.folder, step.name or "", by=by,
                                   held=held)
            return _report(target_id, [report_line(ReportKind.DELETED, rs, path=shown)], rs,
                           status_msg=f"deleted {where}")
        if step.action is Action.RENAME:
            where = sources.rename(settings, srcs, step.folder, step.name or "",
                                   step.new_name or "", by=by, held=held)
            return _report(target_id, [report_line(
                ReportKind.RENAMED, rs, path=shown, new_name=step.new_name or "")], rs,
                status_msg=f"renamed to {where}")
        if step.action is Action.COMPARE:
            memory.remember(settings, spec.id, memory.Pending(
                "compare", step.folder, step.name, time.time() + rs.switch_window_s))
            return _Answer(target_id, None, status_msg=f"the next program received is "
                                                       f"compared with {shown}")
        if step.action is Action.DIRECTORY:
            folder = "/".join(p for p in (rs.receive_folder, step.folder) if p)
            memory.remember(settings, spec.id, memory.Pending(
                "directory", folder, None, time.time() + rs.directory_expires_s))
            return _Answer(target_id, None, status_msg=f"programs received in the next "
                                                       f"{rs.directory_expires_s:g} s go to "
                                                       f"{folder}")
        if step.action is Action.SKIP:
            return _Answer(target_id, None, state=TargetState.SKIPPED,
                           status_msg=f"skipped: {step.note or step.action.value}")
        return _Answer(target_id, None, status_msg=step.note or step.action.value)
    except ContractError as exc:
        return _error_answer(target_id, exc, shown, rs)
    except restart.RestartError as exc:
        error = ContractError(ErrorCode.BAD_PARAMETER, f"cannot restart {shown} from "
                                                       f"{step.restart_block}: {exc.reason}")
        return _error_answer(target_id, error, shown, rs)


def _error_answer(target_id: int, exc: ContractError, shown: str,
                  rs: RequestSettings) -> _Answer:
    """The report that tells the operator what went wrong."""
    if exc.code is ErrorCode.PATH_NOT_FOUND:
        line = report_line(ReportKind.NOT_FOUND, rs, path=shown)
    else:
        line = report_line(ReportKind.FAILED, rs, path=shown, reason=_said(exc))
    return _report(target_id, error_lines(line), rs, error=exc)


def restarted(program: bytes, block: str) -> bytes:
    """The program restarted from `block` (`N100`, or a tool: `T7`) behind a safe-start
    header, its name line first, so that the control stores it under the same name."""
    lines = [line.decode("latin-1") for line in LINE_END.split(program)]
    point = (restart.RestartPoint.parse(from_tool=block) if block[:1].upper() == "T"
             else restart.RestartPoint.parse(from_block=block))
    # Planned on the file's own lines, as `dncq run --from` plans it: the header's
    # "RESTART AT LINE n" is the line of the program as stored, the same in both.
    planned = restart.plan_restart(iter(lines), point)
    body = [(number, line) for number, line in enumerate(lines, 1)
            if line.strip() and line.strip() != "%"]
    named = bool(body) and program_name(body[0][1].encode("latin-1")) is not None
    rest = [line for number, line in body[named:] if number >= planned.start_line]
    out = [line for _, line in body[:named]] + planned.header + rest
    return ("%\n" + "\n".join(out) + "\n%\n").encode("latin-1")


def _deliver(settings: Settings, answers: list[_Answer], answerer: Answerer,
             job_id: str) -> None:
    """Send the answers in order and record each target; after a delivery fails the rest
    are not tried (the control is no longer waiting), and fail with the same reason."""
    cut: ContractError | None = None
    for answer in answers:
        sent: tuple[str, bytes] | None = None
        if answer.program is not None and cut is None:
            try:
                answerer.deliver(answer.name, answer.program, answer.report)
                sent = (answer.name, answer.program)
            except ContractError as exc:
                cut = exc
        if answer.program is not None and sent is None and cut is not None:
            record.finish(settings=settings, target_id=answer.target_id, error=cut,
                          status_msg=answer.status_msg)
            continue
        record.finish(settings=settings, target_id=answer.target_id, error=answer.error,
                      status_msg=answer.status_msg, state=answer.state, answer=sent)


@contextlib.contextmanager
def _leases_kept(settings: Settings, job_id: str) -> Iterator[None]:
    """Keep the job's running targets leased while the answers wait for the control."""
    done = threading.Event()

    def keep() -> None:
        while not done.wait(settings.lease_ttl_s / 3):
            try:
                record.extend(settings=settings, job_id=job_id)
            except Exception:  # the next round tries again; the lease outlives one miss
                log.exception("keeping request %s leased failed", job_id)

    thread = threading.Thread(target=keep, name="dncq-request-lease", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()


def _said(exc: ContractError) -> str:
    """An error in words for the operator's screen."""
    return exc.status_msg or MESSAGES[exc.code]


def _shown(folder: str, name: str) -> str:
    return f"{folder}/{name}" if folder and name else folder or name


def _by(spec: MachineSpec, origin: str) -> str:
    return f"machine:{spec.id} ({origin})"
