"""One drip-feed run on one machine: the program streamed from the store, its line recorded.

Called by the runner for a `dnc_run` target while it holds the machine's lease (renewed
for the whole run by the runner's heartbeat). The database hears of the run's line twice a
second, with every other run of the worker's (worker.drip_board), not at every line: a
1,000-blocks-per-second run costs the same as a slow one.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
from collections.abc import Iterator

from jobs import db
from jobs.dnc import feeding, programs
from jobs.errors import ContractError, ErrorCode
from jobs.fleet.rules import MachineFiles
from jobs.models import RunState, TargetState
from jobs.run.work import Work
from jobs.settings import Settings
from worker import drip_board
from worker.transports.drip import LinkLost

log = logging.getLogger(__name__)


class _Lines:
    """Maps the lines the link counts (header, then program) to the program file's lines."""

    def __init__(self, ticket: feeding.Ticket) -> None:
        self.header = len(ticket.header)
        self.start_line = ticket.start_line

    def file_line(self, running: int) -> int:
        """The file line of the `running`th line sent; before it, the last line skipped."""
        return feeding.file_line(start_line=self.start_line, header_lines=self.header,
                                 running=running)


def execute(settings: Settings, files: MachineFiles, work: Work) -> tuple[
        TargetState, ContractError | None, str | None]:
    """Run the target's program; returns (state, error, status message) for its result."""
    url = settings.resolved_database_url
    ticket = feeding.begin(url=url, job_id=work.job.job_id, machine_id=work.machine_id,
                           attempt=work.attempt, lease_ttl_s=settings.lease_ttl_s)
    mapping = _Lines(ticket)
    board = drip_board.board_for(url)
    entry = board.join(ticket.run_id)  # how far the machine got
    entry.moved(mapping.file_line(0), 0)
    return _feed(settings, files, ticket, mapping, board, entry)


def _feed(settings: Settings, files: MachineFiles, ticket: feeding.Ticket, mapping: _Lines,
          board: drip_board.Board, entry: drip_board.Entry
          ) -> tuple[TargetState, ContractError | None, str | None]:
    """Stream the program and record how the run ended."""
    url = settings.resolved_database_url
    source = _program(settings, ticket, files.encoding)

    def on_line(running: int, sent: int) -> None:
        entry.moved(mapping.file_line(running), sent)

    def should_stop() -> bool:
        entry.alive()  # the record says the link is up while it is
        return entry.stop

    try:
        try:
            result = files.drip_feed(ticket.program_name, source,
                                     total_lines=len(ticket.header) + ticket.lines_total
                                     - ticket.start_line + 1,
                                     on_line=on_line, should_stop=should_stop)
        finally:
            board.leave(entry)  # before the end is recorded: no line is written after it
    except LinkLost as exc:
        last = mapping.file_line(exc.last_line)
        held = mapping.file_line(exc.lines_sent)
        message = f"link lost at line {last}: {exc}; " \
                  f"{feeding.restart_hint(last_line=last, held_line=held)}"
        _end_run(settings, ticket.run_id, state=RunState.FAILED, last_line=last,
                 lines_sent=exc.lines_sent, message=message)
        # Not transient: the machine may have cut, so a next attempt is refused (feeding.begin).
        return TargetState.FAILED, ContractError(ErrorCode.CONNECTION_FAILED, message,
                                                 transient=False), None
    except ContractError as exc:
        if entry.lines_sent == 0 and exc.transient:  # the machine saw nothing: try again later
            stopped = feeding.not_started(url=url, run_id=ticket.run_id,
                                          message=exc.status_msg or "")
            if stopped is None:
                return TargetState.FAILED, exc, None
            return TargetState.CANCELLED, ContractError(ErrorCode.CANCELLED, stopped), None
        last, said = entry.last_line, exc.status_msg or exc.code.name
        if entry.lines_sent:  # as for a lost link: the control may run on through its lines
            held = mapping.file_line(entry.lines_sent)
            message = f"{said} (at line {last}); " \
                      f"{feeding.restart_hint(last_line=last, held_line=held)}"
        else:
            message = f"{said} (before its first line)"
        _end_run(settings, ticket.run_id, state=RunState.FAILED, last_line=last,
                 lines_sent=entry.lines_sent, message=message)
        return TargetState.FAILED, ContractError(exc.code, message, transient=False), None
    except BaseException as exc:
        if entry.lines_sent and db.unreachable(exc):
            # As for a lost link: the machine may have cut, so a next attempt would be
            # refused (feeding.begin). Its end is recorded with the lines the message names,
            # once the database is back (not left to the target's words, and stale counts).
            held = mapping.file_line(entry.lines_sent)
            message = f"database unavailable ({type(exc).__name__}) at line " \
                      f"{entry.last_line}; " \
                      f"{feeding.restart_hint(last_line=entry.last_line, held_line=held)}"
            _end_run(settings, ticket.run_id, state=RunState.FAILED, last_line=entry.last_line,
                     lines_sent=entry.lines_sent, message=message)
            return TargetState.FAILED, ContractError(ErrorCode.INTERNAL_ERROR, message,
                                                     transient=False), None
        if db.unreachable(exc):  # before the first line: the machine saw nothing
            with contextlib.suppress(Exception):  # still lost: the next attempt refuses
                feeding.not_started(url=url, run_id=ticket.run_id,
                                    message=f"database unavailable ({type(exc).__name__})")
            raise  # tried again, as the runner tries a lost database
        # A bug: the run is over for the machine (its link is closed with the attempt), and
        # the record says where it was.
        feeding.end(url=url, run_id=ticket.run_id, state=RunState.FAILED,
                    last_line=entry.last_line, lines_sent=entry.lines_sent,
                    message="the run ended unexpectedly")
        raise
    last = mapping.file_line(result.last_line)
    if result.stopped:
        message = feeding.stopped_message(stopped_by=entry.stopped_by, line=last,
                                          said=result.stop_said)
        _end_run(settings, ticket.run_id, state=RunState.STOPPED, last_line=last,
                 lines_sent=result.lines_sent, message=message)
        return TargetState.CANCELLED, ContractError(ErrorCode.CANCELLED, message), None
    message = f"ran to line {last}"
    _end_run(settings, ticket.run_id, state=RunState.SUCCEEDED, last_line=last,
             lines_sent=result.lines_sent, message=message)
    return TargetState.SUCCEEDED, None, message


def _end_run(settings: Settings, run_id: int, *, state: RunState, last_line: int,
             lines_sent: int, message: str) -> None:
    """Record how the run ended, as the machine said. A database lost just then is waited
    for up to half the lease (the target is recorded next, before the lease runs out and
    its next attempt is refused); lost for longer, it does not change what the machine did
    (a program run to its end is not a failed run): the runner records the target, and
    closes the run with its words (jobs.dnc.runs.close_unstarted)."""
    def waits(exc: BaseException) -> None:
        log.warning("run %s ended (%s); its end waits for the database (%s)", run_id,
                    message, type(exc).__name__)

    try:
        db.when_reachable(lambda: feeding.end(
            url=settings.resolved_database_url, run_id=run_id, state=state,
            last_line=last_line, lines_sent=lines_sent, message=message),
            wait_s=settings.lease_ttl_s / 2, on_wait=waits)
    except Exception as exc:
        if not db.unreachable(exc):
            raise
        log.warning("run %s ended (%s), not recorded: database unavailable (%s); recorded "
                    "with its target", run_id, message, type(exc).__name__)


def _program(settings: Settings, ticket: feeding.Ticket, encoding: str) -> Iterator[bytes]:
    """The lines to send: the restart header, then the program from its start line."""
    header = (line.encode(encoding, errors="strict") for line in ticket.header)
    return itertools.chain(header, programs.lines(settings, ticket.program_id,
                                                  start_line=ticket.start_line))
