"""Drip-feed runs as they are asked: start one, stop it, and close those whose target ended.

A run is a job of kind `dnc_run` with one target per machine and, beside each target, a
`Run` row: what is sent (the stored program, the restart header, the line it starts
from) and how far the machine got. The runner moves the row (jobs.dnc.feeding); the API,
the CLI and the dashboard read it (jobs.dnc.run_views).

A run is never started twice by itself: a program restarted from its first line after
the machine has already cut half of it would cut the part again. A run whose worker died
ends failed with its last confirmed line, and a new run restarts from there on request.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import func, select, true, update
from sqlalchemy.orm import Session

from jobs import rollout, service
from jobs.db import in_chunks, rowcount, session_scope, write_first
from jobs.dnc.programs import ProgramInfo
from jobs.errors import ContractError, ErrorCode
from jobs.job_options import JobOptions
from jobs.models import (
    ACTIVE_STATES,
    Job,
    JobKind,
    Machine,
    Run,
    RunState,
    Target,
    TargetState,
    utcnow,
)
from jobs.settings import Settings

ENDED = (RunState.SUCCEEDED, RunState.STOPPED, RunState.FAILED, RunState.CANCELLED)


@dataclass(frozen=True)
class Restart:
    """Where a run starts when it does not start at the top: a header, then `start_line`."""

    start_line: int  # 1-based line of the program's file
    header: list[str]  # safe start and the modal state, sent first
    asked: str  # as the user wrote it: "N1234", "line 48213", "T7"


def submit(*, session: Session, settings: Settings, machine_ids: Sequence[str],
           program: ProgramInfo, file_name: str, restart: Restart | None = None,
           created_by: str = "api", queue: bool = False) -> Job:
    """Start `program` on each machine (one run each), commit, and queue the runs.

    Raises:
        ContractError: 20007 when a machine has a run queued or running, unless `queue`
            (this run then waits behind it).
    """
    unique = list(dict.fromkeys(machine_ids))
    if not unique:
        raise ContractError(ErrorCode.BAD_PARAMETER, "a run needs a machine")
    hold_machines(session, unique)
    _close_ended(session, unique, heard_since=utcnow() - timedelta(seconds=settings.lease_ttl_s))
    if not queue:
        _refuse_busy(session, unique)
    targets = [service.TargetIn(machineID=m, fileName=file_name) for m in unique]

    def record_runs(job: Job) -> None:
        session.add_all(Run(
            job_id=job.id, position=position, machine_id=machine_id, program_name=file_name,
            program_id=program.id, started_by=created_by, lines_total=program.lines,
            start_line=restart.start_line if restart else 1,
            header=restart.header if restart else [],
            restart_from=restart.asked if restart else None,
            state=RunState.QUEUED, lines_sent=0, last_line=0, stop_requested=False,
            updated_at=utcnow()) for position, machine_id in enumerate(unique))
        session.flush()
        _close_unstarted(session, job.id)  # an unknown machine's target failed at once

    # One attempt while the machine may be running it: the runner retries only a run that
    # never sent a line (the control not yet in DNC mode, an unreachable link).
    return rollout.submit(session=session, settings=settings, kind=JobKind.DNC_RUN,
                          targets=targets, options=JobOptions(), created_by=created_by,
                          recorded=record_runs)


def hold_machines(session: Session, machine_ids: list[str]) -> None:
    """Hold the machines' rows (PostgreSQL; SQLite's write lock) until the commit: of two
    runs asked at once of one machine, the second reads the first's run, not what was there
    before it."""
    write_first(session)
    for chunk in in_chunks(sorted(machine_ids)):  # one order: two jobs never wait crosswise
        session.execute(select(Machine.id).where(Machine.id.in_(chunk)).order_by(Machine.id)
                        .with_for_update())


def _close_ended(session: Session, machine_ids: list[str], *, heard_since: datetime) -> None:
    """Close the machines' runs whose target ended and whose end went unrecorded (a worker
    lost after the stop, a machine removed, a follow-up lost): they hold the machine no
    longer. A stopped one heard of since `heard_since` may still be fed: it stays."""
    ended: set[tuple[str, str]] = set()
    for chunk in in_chunks(machine_ids):
        ended.update(session.execute(
            select(Run.job_id, Run.machine_id)
            .join(Target, (Target.job_id == Run.job_id) & (Target.machine_id == Run.machine_id))
            .where(Run.machine_id.in_(chunk), Run.state.in_((RunState.QUEUED, RunState.RUNNING)),
                   Target.state.not_in(ACTIVE_STATES))).all())
    for job_id, machine_id in sorted(ended):
        _close_unstarted(session, job_id, machine_id=machine_id, heard_since=heard_since)


def _refuse_busy(session: Session, machine_ids: list[str]) -> None:
    """20007 naming the run a machine has queued or running: a run queued behind it
    unasked starts cutting from its top the moment that one is stopped."""
    busy: list[Run] = []
    for chunk in in_chunks(machine_ids):
        busy += session.scalars(select(Run).where(
            Run.machine_id.in_(chunk), Run.state.in_((RunState.QUEUED, RunState.RUNNING))))
    if not busy:
        return
    held = min(busy, key=lambda r: r.id)  # the oldest: running, or the next to run
    doing = "queued" if held.state is RunState.QUEUED else \
        f"running at line {held.last_line:,}" if held.last_line else \
        "running (no line confirmed yet)"
    others = len({r.machine_id for r in busy} - {held.machine_id})
    also = "" if not others else ", and another machine has one too" if others == 1 \
        else f", and {others} other machines have one too"
    raise ContractError(ErrorCode.MACHINE_BUSY, (
        f"machine {held.machine_id} has a drip-feed run {doing} (job {held.job_id}, "
        f"{held.program_name}){also}; stop it first (dncq stop {held.job_id}), or queue "
        "this run behind it (dncq run --queue, \"queue\": true): it then starts when that "
        "one ends, however it ends"))


def unstarted_message(*, stopped_by: str | None) -> str:
    """A run stopped before it started, in words, naming who asked it (when known)."""
    return f"stopped by {stopped_by} before it started" if stopped_by else \
        "stopped before it started"


def request_stop(*, session: Session, settings: Settings, job_id: str, stopped_by: str) -> int:
    """Stop the job's runs: running ones reset their machine, queued ones never start, and
    a stopped one whose target ended unheard of for a lease period (its worker lost) ends.
    `stopped_by` is recorded with each run, its end and the job's view name it (the first
    to ask, when two did).

    Returns how many runs were asked to stop, cancelled or ended.
    """
    job = service.get_job(session=session, job_id=job_id)
    if job.kind is not JobKind.DNC_RUN:
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            f"job {job_id} is a {job.kind.value} job, not a drip-feed run; "
                            "cancel it instead")
    asked = rowcount(session.execute(
        update(Run).where(Run.job_id == job_id, Run.state == RunState.RUNNING,
                          Run.stop_requested.is_(False))
        .values(stop_requested=True, stopped_by=stopped_by, updated_at=utcnow())))
    # A queued run whose target a runner has claimed already must not start either.
    session.execute(update(Run).where(Run.job_id == job_id, Run.state == RunState.QUEUED)
                    .values(stop_requested=True,
                            stopped_by=func.coalesce(Run.stopped_by, stopped_by)))
    service.cancel(session=session, job_id=job_id,  # targets not started
                   status_msg=unstarted_message(stopped_by=stopped_by))
    session.flush()
    return asked + _close_unstarted(
        session, job_id, heard_since=utcnow() - timedelta(seconds=settings.lease_ttl_s))


def close_unstarted(*, url: str, job_id: str, machine_id: str | None = None) -> int:
    """End the job's runs whose target ended before they started (the last attempt found
    the link down), or ended with the end of the run unrecorded (the database was lost:
    its line counts stay the last written, its message names where it ended); returns how
    many; only `machine_id`'s when given (the runner's, after that machine's
    attempt: a run on many machines reads each once, not all after each). A run left
    queued or running kept `dncq run` waiting for ever."""
    with session_scope(url) as session:
        return _close_unstarted(session, job_id, after_attempt=True, machine_id=machine_id)


def _close_unstarted(session: Session, job_id: str, *, after_attempt: bool = False,
                     machine_id: str | None = None, heard_since: datetime | None = None) -> int:
    """Runs whose target ended before they started: cancelled (or failed) with the target,
    and its reason (`the control is in MEM mode`), not only its code's words (`Machine is
    busy.`). A failed or succeeded target's run still running is closed too, as its target
    says: its attempt is over; and a cancelled one's that was asked to stop, as stopped,
    `after_attempt` (the runner's, once it recorded its target) or when not heard of since
    `heard_since` (a run fed writes its record twice a second: no worker feeds it)."""
    ended = list(session.execute(
        select(Target.machine_id, Target.state,
               func.coalesce(Target.status_msg, Target.error_msg))
        .where(Target.job_id == job_id, Target.state.in_(_RUN_OF_TARGET),
               true() if machine_id is None else Target.machine_id == machine_id)))
    closed = 0
    for machine_id, state, why in ended:
        # A cancelled target's run may run on elsewhere (its worker's lease ran out): the
        # stop it was asked for ends it.
        open_states = [RunState.QUEUED] if state is TargetState.CANCELLED \
            else [RunState.QUEUED, RunState.RUNNING]
        closed += rowcount(session.execute(
            update(Run).where(Run.job_id == job_id, Run.machine_id == machine_id,
                              Run.state.in_(open_states))
            .values(state=_RUN_OF_TARGET[state], message=why, ended_at=utcnow(),
                    updated_at=utcnow())))
        if state is TargetState.CANCELLED and (after_attempt or heard_since is not None):
            closed += rowcount(session.execute(  # its stop ended it, unrecorded
                update(Run).where(Run.job_id == job_id, Run.machine_id == machine_id,
                                  Run.state == RunState.RUNNING, Run.stop_requested,
                                  true() if after_attempt else Run.updated_at < heard_since)
                .values(state=RunState.STOPPED, message=why, ended_at=utcnow(),
                        updated_at=utcnow())))
    return closed


_RUN_OF_TARGET = {TargetState.CANCELLED: RunState.CANCELLED, TargetState.FAILED: RunState.FAILED,
                  TargetState.SUCCEEDED: RunState.SUCCEEDED}  # a run's end, by its target's
