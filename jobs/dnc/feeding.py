"""The runner's side of a drip-feed run: begin it, record how far its machine got, see a
stop asked, and end its record; then the run queued behind it on that machine.

A run that began is never begun again from its top (jobs.dnc.runs says why): `begin` ends
it failed instead, with the line to restart from.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import cast

from sqlalchemy import Table, bindparam, select, update
from sqlalchemy.orm import Session

from jobs.db import held, session_scope
from jobs.dnc.runs import ENDED, hold_machines, unstarted_message
from jobs.errors import ContractError, ErrorCode
from jobs.models import Run, RunState, Target, TargetState, utcnow
from jobs.run import running
from jobs.run.leases import LEASE_TTL_S


@dataclass(frozen=True)
class Ticket:
    """What a runner needs to run a program: from `Run`, as plain data."""

    run_id: int
    program_id: str
    program_name: str
    start_line: int
    header: list[str]
    lines_total: int


class Behind(Exception):
    """The attempt steps aside, recording nothing. Either the run waits: another run of its
    machine is being fed (a DNC link feeds one program at a time, whatever the machine's
    max_concurrent), its target is pending again, the attempt neither counted nor recorded,
    and it starts when that run ends. Or the attempt's claim went stale: a later claim of
    its target runs it."""


def begin(*, url: str, job_id: str, machine_id: str, attempt: int,
          lease_ttl_s: float = LEASE_TTL_S) -> Ticket:
    """Mark the run running and return what to send; `attempt` is the target's claim.

    Raises a permanent ContractError when the run must not start: it was stopped, or a
    previous attempt was cut short after the machine may have begun to cut; Behind when
    another run of the machine, heard of within `lease_ttl_s`, is running.
    """
    refusal: Exception | None = None
    with session_scope(url) as session:
        hold_machines(session, [machine_id])  # of two runs queued behind, one starts
        run = session.scalar(select(Run).where(Run.job_id == job_id,
                                               Run.machine_id == machine_id).with_for_update())
        if run is None:
            raise ContractError(ErrorCode.INTERNAL_ERROR, f"job {job_id} has no run record "
                                                          f"for machine {machine_id}")
        if _claim_gone(session, job_id, machine_id, attempt):
            raise Behind(f"attempt {attempt} of job {job_id} on {machine_id} was claimed again")
        if run.state is RunState.FAILED:
            refusal = ContractError(ErrorCode.CONNECTION_FAILED, run.message, transient=False)
        elif run.stop_requested or run.state in ENDED:
            refusal = ContractError(ErrorCode.CANCELLED,
                                    unstarted_message(stopped_by=run.stopped_by))
        elif run.state is RunState.RUNNING:
            # An attempt that never came back (its worker died: `interrupted`): the machine
            # saw the end of its data. Starting the program again from the top would cut
            # what is already cut. The record is written twice a second (worker.drip_board):
            # the lines sent after its last write are not in it, so the machine may hold
            # more than it says.
            message = (f"the worker running it stopped at line {run.last_line}; restart with "
                       f"--from-line at the line the machine shows ({max(run.last_line, 1)} "
                       "or later: it runs on through the lines it held)")
            _end(run, RunState.FAILED, message)
            refusal = ContractError(ErrorCode.CONNECTION_FAILED, message, transient=False)
        elif (ahead := _fed_beside(session, run, heard_since=utcnow()
                                   - timedelta(seconds=lease_ttl_s))) is not None:
            said = f"waits for the run of job {ahead.job_id} ({ahead.program_name}) to end"
            running.put_back(session=session, job_id=job_id, machine_id=machine_id,
                             attempt=attempt, status_msg=said)
            refusal = Behind(said)
        else:
            run.state, run.started_at, run.updated_at = RunState.RUNNING, utcnow(), utcnow()
            ticket = Ticket(run.id, run.program_id, run.program_name, run.start_line,
                            list(run.header), run.lines_total)
    if refusal is not None:  # raised once the record of it is committed
        raise refusal
    return ticket


def _claim_gone(session: Session, job_id: str, machine_id: str, attempt: int) -> bool:
    """Whether the target's claim of `attempt` ran out before its run began: a later claim
    runs the target, or the reaper put it back to wait for one. Either way the run is not
    this attempt's to start, and a run running is not one whose worker stopped."""
    claim = session.execute(select(Target.state, Target.attempts).where(
        Target.job_id == job_id, Target.machine_id == machine_id)).first()
    if claim is None:
        return False
    state, counted = claim
    return counted != attempt if state is TargetState.RUNNING else counted >= attempt


def _fed_beside(session: Session, run: Run, *, heard_since: datetime) -> Run | None:
    """Another run of `run`'s machine running, and heard of since `heard_since` or its
    target under a live lease (a link that reconnects writes no line, while its worker's
    heartbeat keeps the lease); one neither has no worker feeding it. Held until the commit:
    its end, and the look for the run behind it (`next_behind`), come after the run behind
    is put back."""
    return session.scalars(select(Run).join(Target, (Target.job_id == Run.job_id)
                                            & (Target.machine_id == Run.machine_id)).where(
        Run.machine_id == run.machine_id, Run.id != run.id, Run.state == RunState.RUNNING,
        (Run.updated_at >= heard_since) | ((Target.state == TargetState.RUNNING)
                                           & (Target.lease_until > utcnow())))
        .order_by(Run.id).limit(1).with_for_update(of=Run)).first()


def next_behind(*, url: str, job_id: str, machine_id: str) -> str | None:
    """Once the job's run on the machine ended, the job of the oldest run queued behind it
    whose target is due (put back by `begin`), to queue now; else None."""
    with session_scope(url) as session:
        if session.scalar(select(Run.state).where(Run.job_id == job_id,
                                                  Run.machine_id == machine_id)) not in ENDED:
            return None
        return session.scalar(
            select(Run.job_id)
            .join(Target, (Target.job_id == Run.job_id) & (Target.machine_id == Run.machine_id))
            .where(Run.machine_id == machine_id, Run.state == RunState.QUEUED,
                   Target.state == TargetState.PENDING,
                   Target.next_attempt_at.is_(None) | (Target.next_attempt_at <= utcnow()))
            .order_by(Run.id).limit(1))


def file_line(*, start_line: int, header_lines: int, running: int) -> int:
    """The program file's line of the `running`th line a run sent (its restart header
    first, then the file from `start_line`); before the file, the last line skipped."""
    return start_line - 1 + max(running - header_lines, 0)


def restart_hint(*, last_line: int, held_line: int) -> str:
    """Where a run that ended mid-program restarts: at the machine's running line. dncq
    knows it up to `last_line`, the last one the machine confirmed; a control that held the
    lines up to `held_line` runs on through them after its link is gone, and a restart at
    `last_line` would cut those again."""
    if held_line <= last_line:
        return f"restart with --from-line {max(last_line, 1)}"
    return (f"the machine held the lines up to {held_line} and may have run them: restart "
            f"with --from-line at the line it shows ({max(last_line, 1)} to {held_line})")


def not_started(*, url: str, run_id: int, message: str) -> str | None:
    """The attempt sent nothing: the run waits for the next attempt (or ends with the job).

    Returns None while it waits; when a stop came meanwhile the run is cancelled instead,
    and the words it ended with are returned (`stopped by alice before it started`).
    """
    with session_scope(url) as session:
        # Held, on SQLite too (FOR UPDATE takes no lock there): a stop asked meanwhile is
        # seen, not overwritten.
        run = session.scalar(held(session, select(Run).where(Run.id == run_id)))
        if run is None or run.state is not RunState.RUNNING:  # the next attempt decides
            return None
        if run.stop_requested:
            stopped = unstarted_message(stopped_by=run.stopped_by)
            _end(run, RunState.CANCELLED, stopped)
            return stopped
        run.state, run.message, run.updated_at = RunState.QUEUED, message, utcnow()
        return None


@dataclass(frozen=True)
class Line:
    """How far one run's machine got, for `progress_many`."""

    run_id: int
    last_line: int
    lines_sent: int


def progress_many(*, url: str, lines: Sequence[Line]) -> None:
    """Record how far several runs got, in one statement; an ended run is left as it ended."""
    if not lines:
        return
    table = cast(Table, Run.__table__)
    now = utcnow()
    with session_scope(url) as session:
        session.connection().execute(  # one executemany, not the ORM's statement per row
            update(table).where(table.c.id == bindparam("run"),
                                table.c.state == RunState.RUNNING)
            .values(last_line=bindparam("line"), lines_sent=bindparam("sent"),
                    updated_at=now),
            [{"run": x.run_id, "line": x.last_line, "sent": x.lines_sent} for x in lines])


def stopping(*, url: str, run_ids: Sequence[int]) -> dict[int, str | None]:
    """Of `run_ids`, those that must stop (asked to, ended by someone else, or gone), each
    with who asked it to, when someone did."""
    if not run_ids:
        return {}
    with session_scope(url) as session:
        found = {row.id: row for row in session.execute(
            select(Run.id, Run.stop_requested, Run.stopped_by, Run.state)
            .where(Run.id.in_(run_ids)))}
    return {run_id: row.stopped_by if row is not None else None for run_id in run_ids
            if (row := found.get(run_id)) is None
            or row.stop_requested or row.state is not RunState.RUNNING}


def stopped_message(*, stopped_by: str | None, line: int, said: str) -> str:
    """A stopped run's end in words, naming who asked it (when known)."""
    who = f"by {stopped_by}" if stopped_by else "on request"
    return f"stopped {who} at line {line:,}; {said}"


def end(*, url: str, run_id: int, state: RunState, last_line: int, lines_sent: int,
        message: str | None = None) -> None:
    """Record the end of the run."""
    with session_scope(url) as session:
        run = session.get(Run, run_id)
        if run is not None and run.state not in ENDED:  # never over another's end of it
            run.last_line, run.lines_sent = last_line, lines_sent
            _end(run, state, message)


def _end(run: Run, state: RunState, message: str | None) -> None:
    run.state, run.message = state, message
    run.ended_at = run.updated_at = utcnow()
