"""What runners do to targets: begin, and finish-and-claim-next.

The other half of jobs.service (which creates and reads jobs). Job and target state is
written here, there, by jobs.run.reaper (which recovers what dead workers leave) and, for a
streamed backupFiles, by jobs.backup.streamed.
Every transition is a conditional update, so a target that reached a final state is
never run again, whoever asks. The hot path is two steps for a machine with one
target: `begin` (slot + first target) and `finish` (result + next target, or the slot
given back); the steps of every runner in a process share transactions and set-based
statements (jobs.run.group_commit). A target's claim is jobs.run.claims; what an attempt's
end makes of its target and job is jobs.run.outcomes; a running target's own transactions
are jobs.run.running.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Any, cast

from sqlalchemy import Boolean, String, Table, bindparam, exists, func, select, tuple_, update
from sqlalchemy.orm import Session

from jobs.db import insert_rows, session_scope
from jobs.errors import (
    ContractError,
)
from jobs.fleet.registry import MachineSpec
from jobs.job_options import JobOptions
from jobs.models import (
    ACTIVE_STATES,
    Attempt,
    Job,
    JobState,
    Machine,
    Target,
    TargetState,
    utcnow,
)
from jobs.run import leases, outcomes
from jobs.run.claims import claim_many, worker_name
from jobs.run.group_commit import GroupCommit
from jobs.run.settle import cancel_pending, update_job_state
from jobs.run.work import Finished, JobInfo, Report, Started, Work
from jobs.settings import Settings


@dataclass(frozen=True)
class _Begin:
    """A runner asks for a slot of its machine and the job's first due target there."""

    settings: Settings
    job_id: str
    machine_id: str


@dataclass(frozen=True)
class _GiveBack:
    """A runner that failed gives its slot back."""

    holder: str
    machine_id: str


# Statements of the hot path, built once: building SQLAlchemy expressions per call costs
# more CPU than running them (bindparam names differ from column names on purpose).
# Each serves a whole batch of runners (see jobs.run.group_commit).
_T, _J, _M = (cast(Table, m.__table__) for m in (Target, Job, Machine))
# The machines' specs: MachineSpec's fields in its order, so that each row makes one.
_MACHINES = (select(*(_M.c[name] for name in MachineSpec.__dataclass_fields__))
             .where(_M.c.id.in_(bindparam("machine_ids", expanding=True))))
_JOBS = (select(_J.c.id, _J.c.kind, _J.c.options, _J.c.payload_id, _J.c.state, _J.c.created_at)
         .where(_J.c.id.in_(bindparam("job_ids", expanding=True))))
_ATTEMPTS = cast(Table, Attempt.__table__)
# Targets whose attempts ended alike (a rollout's successes: the same state, result and
# times) are settled by one statement; an UPDATE per target, run as an executemany, cost
# its Python per row. Each by (id, attempt): a report settles only the attempt running.
_SETTLE = (
    update(_T).where(tuple_(_T.c.id, _T.c.attempts).in_(bindparam("claims", expanding=True)),
                     _T.c.state == TargetState.RUNNING)
    .values(state=bindparam("new_state"), next_attempt_at=bindparam("next_at"),
            finished_at=bindparam("done_at"), error_code=bindparam("code"),
            error_msg=bindparam("msg"), status_msg=bindparam("status"),
            dispatched_at=bindparam("queued_at"), lease_until=None,
            # Once an attempt was cut off, the target remembers it through every attempt
            # after: one that found the machine offline wrote nothing and proves nothing.
            interrupted=_T.c.interrupted | bindparam("cut_off", type_=Boolean()),
            replaced_payload_id=func.coalesce(bindparam("replaced", type_=String()),
                                              _T.c.replaced_payload_id))
    .returning(_T.c.id, _T.c.attempts))
# Jobs with due targets that nobody has queued (they found the machine busy), oldest first.
_WAITING = (
    select(_T.c.machine_id, _T.c.job_id).join(_J, _J.c.id == _T.c.job_id)
    .where(_T.c.machine_id.in_(bindparam("machine_ids", expanding=True)),
           _T.c.state == TargetState.PENDING, _T.c.dispatched_at.is_(None),
           _T.c.next_attempt_at.is_(None) | (_T.c.next_attempt_at <= bindparam("now")))
    .group_by(_T.c.machine_id, _T.c.job_id, _J.c.created_at)
    .order_by(_J.c.created_at))
_QUEUED = (update(_T).where(_T.c.job_id == bindparam("of_job"),
                            _T.c.machine_id == bindparam("on_machine"),
                            _T.c.state == TargetState.PENDING)
           .values(dispatched_at=bindparam("queued_at")))
# EXISTS stops at a job's first active target; a DISTINCT over them read every active target
# of the job at each commit, which made a 100,000-target job quadratic.
_STILL_ACTIVE = (select(_J.c.id)
                 .where(_J.c.id.in_(bindparam("job_ids", expanding=True)),
                        exists().where(_T.c.job_id == _J.c.id,
                                       _T.c.state.in_(ACTIVE_STATES))))


def begin(*, settings: Settings, job_id: str, machine_id: str) -> Started:
    """The machine, a slot of it for the job, and the job's first due target (or why not)."""
    return cast(Started, _COMMITS.call(settings.resolved_database_url,
                                       _Begin(settings, job_id, machine_id)))


def finish(*, settings: Settings, work: Work, holder: str, error: ContractError | None,
           state: TargetState = TargetState.SUCCEEDED, status_msg: str | None = None,
           replaced_payload_id: str | None = None) -> Finished:
    """Record the attempt, then claim the next due target or give the machine's slot back."""
    return finish_later(settings=settings, work=work, holder=holder, error=error, state=state,
                        status_msg=status_msg, replaced_payload_id=replaced_payload_id).result()


def finish_later(*, settings: Settings, work: Work, holder: str, error: ContractError | None,
                 state: TargetState = TargetState.SUCCEEDED, status_msg: str | None = None,
                 replaced_payload_id: str | None = None) -> Future[Finished]:
    """`finish` without waiting for the commit; the future gets what is left to do."""
    return cast(Future[Finished], _COMMITS.submit(settings.resolved_database_url, Report(
        settings, work, holder, error, state, status_msg, replaced_payload_id)))


def drain(timeout_s: float) -> bool:
    """Wait until every finish handed over so far is committed (a worker shutting down)."""
    return _COMMITS.drain(timeout_s)


def give_back(*, settings: Settings, holder: str, machine_id: str) -> str | None:
    """Release a slot outside `finish` (a runner that failed); returns a waiting job to queue."""
    return cast(str | None, _COMMITS.call(settings.resolved_database_url,
                                          _GiveBack(holder, machine_id)))


def _serve(session: Session, requests: Sequence[_Begin | Report | _GiveBack]) -> list[Any]:
    """One transaction for a batch of runners: finished attempts first (they free slots)."""
    now = utcnow()
    results: list[Any] = [None] * len(requests)
    for kind, serve_many in _SERVED_IN_ORDER:
        picked = [i for i, r in enumerate(requests) if isinstance(r, kind)]
        if picked:
            served = serve_many(session, [requests[i] for i in picked], now)
            for i, result in zip(picked, served, strict=True):
                results[i] = result
    _settle_ended_jobs(session, requests, results)
    return results


def _give_back_many(session: Session, gives: Sequence[_GiveBack], now: datetime
                    ) -> list[str | None]:
    leases.drop_many(session, [g.holder for g in gives])
    return _take_waiting(session, [g.machine_id for g in gives], now)


_COMMITS = GroupCommit("runner-commits", _serve)


def _begin_many(session: Session, asks: Sequence[_Begin], now: datetime) -> list[Started]:
    conn = session.connection()
    specs = {row.id: MachineSpec(*row) for row in conn.execute(
        _MACHINES, {"machine_ids": _ids(a.machine_id for a in asks)})}
    rows = conn.execute(_JOBS, {"job_ids": _ids(a.job_id for a in asks)}).all()
    jobs = {row.id: JobInfo(row.id, row.kind, JobOptions(**row.options), row.payload_id,
                            row.created_at)
            for row in rows if row.state is not JobState.CANCELLED}
    # A cancelled job's target that came back pending (the reaper's, from a worker lost
    # mid-attempt) is cancelled by the first runner that finds it, not left pending.
    ended = set()
    for job_id in sorted({row.id for row in rows if row.state is JobState.CANCELLED}):
        if cancel_pending(session=session, job_id=job_id, status_msg="cancelled on request") \
                and update_job_state(session=session, job_id=job_id):
            ended.add(job_id)
    results = [Started(specs.get(a.machine_id)) for a in asks]
    for i, a in enumerate(asks):  # one runner of each says that the job ended
        if a.job_id in ended:
            results[i] = replace(results[i], job_done=True)
            ended.discard(a.job_id)
    wanting = [i for i, a in enumerate(asks) if a.machine_id in specs and a.job_id in jobs]
    holders = leases.take_many(session, [
        leases.Want(asks[i].machine_id, specs[asks[i].machine_id].max_concurrent,
                    f"job:{asks[i].job_id}") for i in wanting],
        ttl_s=asks[0].settings.lease_ttl_s)
    busy = [asks[i] for i, h in zip(wanting, holders, strict=True) if h is None]
    if busy:  # whoever frees the machine queues these jobs again
        conn.execute(_QUEUED, [{"of_job": a.job_id, "on_machine": a.machine_id,
                                "queued_at": None} for a in busy])
    slotted = {(asks[i].job_id, asks[i].machine_id): (i, h)
               for i, h in zip(wanting, holders, strict=True) if h is not None}
    claimed = claim_many(session, jobs, list(slotted), asks[0].settings.lease_ttl_s, now,
                          delivered=True)
    idle = []
    for pair, (i, holder) in slotted.items():
        work = claimed.get(pair)
        if work is None:  # nothing due: the slot goes straight back
            idle.append(holder)
        else:
            results[i] = Started(specs[pair[1]], holder, work)
    leases.drop_many(session, idle)
    return results


def _finish_many(session: Session, reports: Sequence[Report], now: datetime) -> list[Finished]:
    conn = session.connection()
    retry_in = [outcomes.retry_delay_s(r.settings, r.work, now) if (
        r.error is not None and r.error.transient) else None for r in reports]
    # A job cancelled while its target ran lets the attempt finish; one that failed then is
    # cancelled rather than retried, which the cancelled job would never start.
    cancelled = _cancelled_jobs(session, [r.work.job.job_id for r, delay
                                          in zip(reports, retry_in, strict=True)
                                          if delay is not None])
    stopped = [delay is not None and r.work.job.job_id in cancelled
               for r, delay in zip(reports, retry_in, strict=True)]
    retry_in = [None if stop else delay for stop, delay in zip(stopped, retry_in, strict=True)]
    alike: dict[tuple[tuple[str, Any], ...], list[tuple[int, int]]] = {}
    for r, delay, stop in zip(reports, retry_in, stopped, strict=True):
        settlement = outcomes.settlement(r, delay, now, cancelled=stop)
        alike.setdefault(tuple(sorted(settlement.items())), []).append(
            (r.work.target_id, r.work.attempt))
    settled: set[tuple[int, int]] = set()
    for values, claims in alike.items():
        settled.update((row.id, row.attempts) for row in conn.execute(
            _SETTLE, {**dict(values), "claims": claims}))
    # A report of an attempt that stalled past its lease, whose target the reaper queued
    # again (and another attempt may run now), settles nothing, asks no retry and counts
    # no failure: it completes the reaper's record of that attempt.
    current = [(r.work.target_id, r.work.attempt) in settled for r in reports]
    retry_in = [delay if ok else None for ok, delay in zip(current, retry_in, strict=True)]
    ended_late = {i for i, r in enumerate(reports)
                  if not current[i] and outcomes.record_late(session, r, now)}
    insert_rows(session, _ATTEMPTS, [{  # by COPY on PostgreSQL: a row's Python is most of it
        "target_id": r.work.target_id, "number": r.work.attempt, "worker": worker_name(),
        "started_at": r.work.started_at, "finished_at": now,
        "error_code": int(r.error.code) if r.error else 0,
        "error_msg": (r.error.status_msg or str(r.error)) if r.error else None}
        for i, r in enumerate(reports) if i not in ended_late])
    aborting = {r.work.job.job_id: r.work.options.abort_after_failures
                for r, delay, ok in zip(reports, retry_in, current, strict=True)
                if ok and r.error is not None and delay is None
                and r.work.options.abort_after_failures}
    for job_id, limit in sorted(aborting.items()):  # locks taken in one order: no deadlock
        outcomes.abort_if_too_many_failures(session, job_id, limit)
    jobs = {r.work.job.job_id: r.work.job for r in reports}
    # A machine's last target of the job was claimed knowing it was the last: nothing to
    # look for (a target put back meanwhile finds the slot held, waits, and is queued below).
    going_on = outcomes.still_usable(session, [
        r for r, delay in zip(reports, retry_in, strict=True) if delay is None and r.work.more])
    # A runner that lost its slot while it stalled takes nothing more: whoever took the
    # slot runs the job's next targets there, and the machine never sees two at once.
    held = leases.kept(session, [r.holder for r in going_on],
                       ttl_s=reports[0].settings.lease_ttl_s)
    going_on = [r for r in going_on if r.holder in held]
    claimed = claim_many(session, jobs, [(r.work.job.job_id, r.work.machine_id)
                                          for r in going_on],
                          reports[0].settings.lease_ttl_s, now)
    next_work = [claimed.get((r.work.job.job_id, r.work.machine_id)) for r in reports]
    freed = [i for i, work in enumerate(next_work) if work is None]
    leases.drop_many(session, [reports[i].holder for i in freed])
    waiting: list[str | None] = [None] * len(reports)
    for i, waiting_job in zip(freed, _take_waiting(session, [reports[i].work.machine_id
                                                            for i in freed], now),
                              strict=True):
        waiting[i] = waiting_job
    return [Finished(next_work[i], retry_in[i], waiting[i]) for i in range(len(reports))]


def _settle_ended_jobs(session: Session, requests: Sequence[_Begin | Report | _GiveBack],
                       results: list[Any]) -> None:
    """The jobs of this transaction's finished attempts that have no target left to run are
    settled, and one report of each (the last) says the job is done.

    A job of which this transaction claimed a target is running still. Only the others are
    looked up: in a rollout's backlog every transaction claims targets of it, and the
    lookup, however it is indexed, reads past the targets it had finished.
    """
    reports = [(i, r) for i, r in enumerate(requests) if isinstance(r, Report)]
    if not reports:
        return
    jobs = {r.work.job.job_id for _, r in reports}
    claimed = {work.job.job_id for work in (
        result.work if isinstance(result, Started) else
        result.next_work if isinstance(result, Finished) else None
        for result in results) if work is not None}
    active = set(claimed)
    if asked := jobs - claimed:
        active.update(session.connection().execute(
            _STILL_ACTIVE, {"job_ids": list(asked)}).scalars())
    for job_id in sorted(jobs - active):
        update_job_state(session=session, job_id=job_id)
    last_report = {r.work.job.job_id: i for i, r in reports}
    for i, r in reports:
        job_id = r.work.job.job_id
        if job_id not in active and last_report[job_id] == i:
            results[i] = replace(results[i], job_done=True)


# What `_serve` runs for each kind of request, in this order.
_SERVED_IN_ORDER: tuple[tuple[type, Callable[[Session, Any, datetime], Sequence[Any]]], ...] = (
    (Report, _finish_many), (_GiveBack, _give_back_many), (_Begin, _begin_many))


def _ids(values: Iterable[str]) -> list[str]:
    return sorted(set(values))


def _cancelled_jobs(session: Session, job_ids: Sequence[str]) -> set[str]:
    """Which of these jobs were cancelled.

    The rows are held (FOR KEY SHARE) until the attempts are recorded: a cancel locks its
    job's row first (jobs.service.cancel), so it either commits before this read, which
    sees it, or waits for the attempts put back to retry, which it then cancels. Unheld,
    a cancel that found the target running and this read that came before its commit left
    the target retrying in a cancelled job. A job being queued (jobs.service.dispatch)
    holds its row too, in a mode this one does not wait for.
    """
    if not job_ids:
        return set()
    ids = _ids(job_ids)
    states = session.connection().execute(
        select(_J.c.id, _J.c.state).where(_J.c.id.in_(ids)).order_by(_J.c.id)
        .with_for_update(read=True, key_share=True)).all()
    return {job_id for job_id, state in states if state is JobState.CANCELLED}


def _take_waiting(session: Session, machine_ids: Sequence[str], now: datetime
                  ) -> list[str | None]:
    """Per freed slot, the oldest job with due targets waiting for its machine, now queued."""
    if not machine_ids:
        return []
    conn = session.connection()
    waiting: dict[str, list[str]] = {}
    for machine_id, job_id in conn.execute(_WAITING, {"machine_ids": _ids(machine_ids),
                                                      "now": now}):
        waiting.setdefault(machine_id, []).append(job_id)
    taken = [waiting[m].pop(0) if waiting.get(m) else None for m in machine_ids]
    queued = [{"of_job": job_id, "on_machine": m, "queued_at": now}
              for m, job_id in zip(machine_ids, taken, strict=True) if job_id]
    if queued:
        conn.execute(_QUEUED, queued)
    return taken


def take_waiting(*, url: str, machine_ids: Sequence[str]) -> list[str | None]:
    """Per machine, the oldest job waiting for it, now marked as queued (for slots held
    outside jobs: single requests, checks, listeners), in one transaction."""
    with session_scope(url) as session:
        return _take_waiting(session, machine_ids, utcnow())
