"""What runners do to targets: begin, finish-and-claim-next, and recovery by the reaper.

The other half of jobs.service (which creates and reads jobs); together they are the
only writers of job and target state. Every transition is a conditional update, so a
target that reached a final state is never run again, whoever asks. The hot path is
two transactions for a machine with one target: `begin` (slot + first target) and
`finish` (result + next target, or the slot given back).
"""

from __future__ import annotations

import os
import random
import socket
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, cast

from sqlalchemy import String, Table, bindparam, func, insert, select, update
from sqlalchemy.orm import Session

from jobs import leases, queue
from jobs.db import rowcount, session_scope
from jobs.errors import TRANSIENT_CODES, ContractError, ErrorCode, result
from jobs.machines import MachineSpec
from jobs.models import (
    Attempt,
    Job,
    JobKind,
    JobState,
    Machine,
    MachineLease,
    Target,
    TargetState,
    utcnow,
)
from jobs.service import JobOptions, update_job_state
from jobs.settings import Settings

INTERRUPTED = "interrupted: worker lost"
ACTIVE = (TargetState.PENDING, TargetState.RUNNING)


@dataclass(frozen=True)
class JobInfo:
    """What a runner needs of the job, read once per task."""

    job_id: str
    kind: JobKind
    options: JobOptions
    payload_id: str | None


@dataclass(frozen=True)
class Work:
    """One claimed target, as plain data for a runner."""

    target_id: int
    job: JobInfo
    machine_id: str
    params: dict[str, Any]
    payload_id: str | None
    attempt: int  # 1 for the first try
    started_at: datetime
    previous_interrupted: bool  # the last attempt died with its worker

    @property
    def kind(self) -> JobKind:
        return self.job.kind

    @property
    def options(self) -> JobOptions:
        return self.job.options


@dataclass(frozen=True)
class Started:
    """What `begin` found: the machine, and when it got a slot, the holder and first target."""

    spec: MachineSpec | None
    holder: str | None = None
    work: Work | None = None


@dataclass(frozen=True)
class Finished:
    """What `finish` left to do: the next target, or a retry or a waiting job to queue."""

    next_work: Work | None
    retry_in_s: float | None = None
    waiting_job_id: str | None = None
    job_done: bool = False  # this attempt was the job's last


# Statements of the hot path, built once: building SQLAlchemy expressions per call costs
# more CPU than running them (bindparam names differ from column names on purpose).
_T, _J, _M = (cast(Table, m.__table__) for m in (Target, Job, Machine))
_MACHINE_AND_JOB = (
    select(_M, _J.c.kind, _J.c.options.label("job_options"), _J.c.payload_id,
           _J.c.state.label("job_state"))
    .select_from(_M.outerjoin(_J, _J.c.id == bindparam("job_id")))
    .where(_M.c.id == bindparam("machine_id")))
# The job's first pending target on the machine, if it is due and the job not cancelled:
# a target waiting for its retry holds the later ones back, so request order is kept.
_CLAIM = (
    update(_T)
    .where(_T.c.id == select(_T.c.id).where(
               _T.c.job_id == bindparam("of_job"), _T.c.machine_id == bindparam("on_machine"),
               _T.c.state == TargetState.PENDING).order_by(_T.c.position).limit(1)
           .scalar_subquery(),
           _T.c.state == TargetState.PENDING,
           _T.c.next_attempt_at.is_(None) | (_T.c.next_attempt_at <= bindparam("now")),
           select(_J.c.id).where(_J.c.id == bindparam("of_job"),
                                 _J.c.state != JobState.CANCELLED).exists())
    .values(state=TargetState.RUNNING, attempts=_T.c.attempts + 1,
            started_at=bindparam("now"), lease_until=bindparam("until"),
            claimed_by=bindparam("worker"))
    .returning(_T.c.id, _T.c.params, _T.c.payload_id, _T.c.attempts, _T.c.interrupted))
_RECORD = insert(cast(Table, Attempt.__table__))
_SETTLE = (
    update(_T).where(_T.c.id == bindparam("target_id"), _T.c.state == TargetState.RUNNING)
    .values(state=bindparam("new_state"), next_attempt_at=bindparam("next_at"),
            finished_at=bindparam("done_at"), error_code=bindparam("code"),
            error_msg=bindparam("msg"), status_msg=bindparam("status"),
            dispatched_at=bindparam("queued_at"), interrupted=False, lease_until=None,
            replaced_payload_id=func.coalesce(bindparam("replaced", type_=String()),
                                              _T.c.replaced_payload_id)))
_WAITING = (
    select(_T.c.job_id).join(_J, _J.c.id == _T.c.job_id)
    .where(_T.c.machine_id == bindparam("machine_id"), _T.c.state == TargetState.PENDING,
           _T.c.dispatched_at.is_(None),
           _T.c.next_attempt_at.is_(None) | (_T.c.next_attempt_at <= bindparam("now")))
    .order_by(_J.c.created_at).limit(1))
_QUEUED = (update(_T).where(_T.c.job_id == bindparam("of_job"),
                            _T.c.machine_id == bindparam("on_machine"),
                            _T.c.state == TargetState.PENDING)
           .values(dispatched_at=bindparam("queued_at")))
_ACTIVE = select(_T.c.id).where(_T.c.job_id == bindparam("job_id"),
                                _T.c.state.in_([TargetState.PENDING, TargetState.RUNNING])
                                ).limit(1)


def begin(*, settings: Settings, job_id: str, machine_id: str) -> Started:
    """In one transaction: the machine, a slot of it for the job, the job's first due target."""
    now = utcnow()
    with session_scope(settings.resolved_database_url) as session:
        conn = session.connection()
        row = conn.execute(_MACHINE_AND_JOB,
                           {"machine_id": machine_id, "job_id": job_id}).mappings().first()
        if row is None:
            return Started(None)
        spec = MachineSpec(**{f: row[f] for f in MachineSpec.__dataclass_fields__})
        job = _as_job_info(job_id, row)
        if job is None:
            return Started(spec)
        holder = leases.take(session, machine_id=machine_id, max_concurrent=spec.max_concurrent,
                             group=f"job:{job_id}", ttl_s=settings.lease_ttl_s)
        if holder is None:  # busy: whoever frees the machine queues this job again
            _mark_waiting(session, job_id, machine_id)
            return Started(spec)
        work = _claim(session, job, machine_id, settings.lease_ttl_s, now)
        if work is None:
            leases.drop(session, holder=holder)
            return Started(spec)
        return Started(spec, holder, work)


def _as_job_info(job_id: str, row: Any) -> JobInfo | None:
    if row["job_state"] is None or row["job_state"] is JobState.CANCELLED:
        return None
    return JobInfo(job_id, row["kind"], JobOptions(**row["job_options"]), row["payload_id"])


def _claim(session: Session, job: JobInfo, machine_id: str, lease_s: float,
           now: datetime) -> Work | None:
    row = session.connection().execute(_CLAIM, {
        "of_job": job.job_id, "on_machine": machine_id, "now": now,
        "until": now + timedelta(seconds=lease_s), "worker": worker_name()}).first()
    if row is None:
        return None
    return Work(row.id, job, machine_id, dict(row.params), row.payload_id or job.payload_id,
                row.attempts, now, bool(row.interrupted))


def finish(*, settings: Settings, work: Work, holder: str, error: ContractError | None,
           state: TargetState = TargetState.SUCCEEDED, status_msg: str | None = None,
           replaced_payload_id: str | None = None) -> Finished:
    """Record the attempt, then claim the next due target or give the machine's slot back."""
    now = utcnow()
    retry_in = _retry_delay_s(settings, work, now) if (
        error is not None and error.code in TRANSIENT_CODES) else None
    with session_scope(settings.resolved_database_url) as session:
        conn = session.connection()
        conn.execute(_RECORD, {
            "target_id": work.target_id, "number": work.attempt, "worker": worker_name(),
            "started_at": work.started_at, "finished_at": now,
            "error_code": int(error.code) if error else 0,
            "error_msg": (error.status_msg or str(error)) if error else None})
        settle: dict[str, Any] = {"target_id": work.target_id, "replaced": replaced_payload_id,
                                  "next_at": None, "done_at": now, "queued_at": now}
        if retry_in is not None:
            assert error is not None
            settle.update(
                new_state=TargetState.PENDING, next_at=now + timedelta(seconds=retry_in),
                done_at=None, queued_at=None, code=int(error.code),
                msg=error.body()["errorMsg"],
                status=f"attempt {work.attempt} failed ({error.status_msg or ''}); "
                       f"retrying in {retry_in:.0f} s")
        else:
            body = error.body() if error else result(ErrorCode.SUCCESS, status_msg)
            settle.update(new_state=TargetState.FAILED if error else state,
                          code=body["errorCode"], msg=body["errorMsg"],
                          status=body.get("statusMsg"))
        conn.execute(_SETTLE, settle)
        if error is not None and retry_in is None and work.options.abort_after_failures:
            _abort_if_too_many_failures(session, work.job.job_id,
                                        work.options.abort_after_failures)
        next_work = None
        if retry_in is None:
            next_work = _claim(session, work.job, work.machine_id, settings.lease_ttl_s, now)
        waiting = None
        if next_work is None:
            leases.drop(session, holder=holder)
            waiting = _take_waiting(session, work.machine_id, now)
        job_done = conn.execute(_ACTIVE, {"job_id": work.job.job_id}).first() is None
        if job_done:
            update_job_state(session, work.job.job_id)
    return Finished(next_work, retry_in, waiting, job_done)


def give_back(*, settings: Settings, holder: str, machine_id: str) -> str | None:
    """Release a slot outside `finish` (a runner that failed); returns a waiting job to queue."""
    with session_scope(settings.resolved_database_url) as session:
        leases.drop(session, holder=holder)
        return _take_waiting(session, machine_id, utcnow())


def _retry_delay_s(settings: Settings, work: Work, now: datetime) -> float | None:
    delay = min(settings.retry_max_s, settings.retry_base_s * 2 ** (work.attempt - 1))
    delay *= random.uniform(0.5, 1.5)  # jitter: a fleet that failed together retries apart
    window = work.options.deliver_within
    if window is not None:
        with session_scope(settings.resolved_database_url) as session:
            created = session.scalar(select(Job.created_at).where(Job.id == work.job.job_id))
        assert created is not None
        remaining = (created + timedelta(seconds=window) - now).total_seconds()
        return min(delay, remaining) if remaining > 0 else None
    max_attempts = work.options.max_attempts or settings.max_attempts
    return delay if work.attempt < max_attempts else None


def _abort_if_too_many_failures(session: Session, job_id: str, limit: int) -> None:
    failed = session.scalar(select(func.count()).where(
        Target.job_id == job_id, Target.state == TargetState.FAILED)) or 0
    if failed >= limit:
        session.execute(
            update(Target).where(Target.job_id == job_id, Target.state == TargetState.PENDING)
            .values(state=TargetState.CANCELLED, error_code=int(ErrorCode.CANCELLED),
                    error_msg="Cancelled.", finished_at=utcnow(),
                    status_msg=f"rollout aborted after {failed} failed targets"))


def _mark_waiting(session: Session, job_id: str, machine_id: str) -> None:
    session.connection().execute(_QUEUED, {"of_job": job_id, "on_machine": machine_id,
                                           "queued_at": None})


def _take_waiting(session: Session, machine_id: str, now: datetime) -> str | None:
    """The oldest job with due targets waiting for this machine, marked as queued."""
    conn = session.connection()
    job_id = conn.execute(_WAITING, {"machine_id": machine_id, "now": now}).scalar()
    if job_id:
        conn.execute(_QUEUED, {"of_job": job_id, "on_machine": machine_id, "queued_at": now})
    return job_id


def take_waiting(*, url: str, machine_id: str) -> str | None:
    """The oldest job waiting for this machine, now marked as queued (for single requests)."""
    with session_scope(url) as session:
        return _take_waiting(session, machine_id, utcnow())


def extend_running(*, url: str, job_id: str, machine_id: str, lease_s: float) -> None:
    """Heartbeat: the job's running targets on the machine are still being worked on."""
    with session_scope(url) as session:
        session.execute(update(Target).where(
            Target.job_id == job_id, Target.machine_id == machine_id,
            Target.state == TargetState.RUNNING)
            .values(lease_until=utcnow() + timedelta(seconds=lease_s)))


def report_bytes(*, url: str, target_id: int, done: int, total: int | None) -> None:
    """Progress of a large transfer."""
    with session_scope(url) as session:
        session.execute(update(Target).where(Target.id == target_id)
                        .values(bytes_done=done, bytes_total=total))


def reap(*, settings: Settings) -> int:
    """Requeue what a dead worker or a lost queue left behind; returns the groups queued.

    Running targets whose lease expired go back to pending (their attempt is recorded
    as interrupted); pending, due targets not queued recently are queued again when
    their machine has a free slot.
    """
    now = utcnow()
    with session_scope(settings.resolved_database_url) as session:
        stale = session.execute(
            select(Target.id, Target.attempts, Target.started_at, Target.claimed_by).where(
                Target.state == TargetState.RUNNING, Target.lease_until < now)).all()
        for target_id, attempts, started_at, claimed_by in stale:
            moved = rowcount(session.execute(
                update(Target).where(Target.id == target_id, Target.state == TargetState.RUNNING,
                                     Target.lease_until < now)
                .values(state=TargetState.PENDING, lease_until=None, dispatched_at=None,
                        interrupted=True, status_msg="its worker was lost; queued again")
            ))
            if moved:
                session.add(Attempt(target_id=target_id, number=attempts,
                                    worker=claimed_by or "",
                                    started_at=started_at or now, finished_at=now,
                                    error_msg=INTERRUPTED))
        redispatch_before = now - timedelta(seconds=settings.redispatch_after_s)
        due = session.execute(
            select(Target.job_id, Target.machine_id).where(
                Target.state == TargetState.PENDING,
                (Target.next_attempt_at.is_(None)) | (Target.next_attempt_at <= now),
                (Target.dispatched_at.is_(None)) | (Target.dispatched_at < redispatch_before))
            .distinct()).all()
        groups = [(j, m) for j, m in due if _has_free_slot(session, m, now)]
        for job_id, machine_id in groups:
            session.execute(update(Target).where(
                Target.job_id == job_id, Target.machine_id == machine_id,
                Target.state == TargetState.PENDING).values(dispatched_at=now))
    for job_id, machine_id in groups:
        queue.enqueue_machine(settings, job_id, machine_id)
    _settle_finished_jobs(settings)
    _assemble_forgotten_backups(settings, now)
    return len(groups)


def _settle_finished_jobs(settings: Settings) -> None:
    """Jobs whose last targets finished at the same moment, each runner seeing the other
    still running, so that none settled the job: settle them now."""
    with session_scope(settings.resolved_database_url) as session:
        unsettled = session.scalars(select(Job.id).where(
            Job.state.in_([JobState.QUEUED, JobState.RUNNING]),
            ~select(Target.id).where(Target.job_id == Job.id,
                                     Target.state.in_(ACTIVE)).exists())).all()
        for job_id in unsettled:
            update_job_state(session, job_id)


_ASSEMBLY_ASKED: dict[str, datetime] = {}  # job -> when this process last queued its assembly


def _assemble_forgotten_backups(settings: Settings, now: datetime) -> None:
    """Backup jobs that finished without their ZIP (a worker died, a cancel ended them)."""
    from jobs.models import Backup

    settled = now - timedelta(seconds=2)
    with session_scope(settings.resolved_database_url) as session:
        forgotten = session.scalars(select(Job.id).where(
            Job.kind == JobKind.BACKUP, Job.finished_at.is_not(None), Job.finished_at < settled,
            Job.finished_at > now - timedelta(days=1),
            ~select(Backup.id).where(Backup.job_id == Job.id).exists())).all()
    for job_id in forgotten:
        asked = _ASSEMBLY_ASKED.get(job_id)
        if asked is None or now - asked > timedelta(minutes=5):
            _ASSEMBLY_ASKED[job_id] = now
            queue.enqueue_assembly(settings, job_id)


def _has_free_slot(session: Session, machine_id: str, now: datetime) -> bool:
    limit = session.scalar(select(Machine.max_concurrent).where(Machine.id == machine_id)) or 1
    held = session.scalar(select(func.count()).where(
        MachineLease.machine_id == machine_id, MachineLease.expires_at >= now)) or 0
    return held < limit


def worker_name() -> str:
    """Who runs an attempt, for its record: host and process."""
    return f"{_HOST}:{os.getpid()}"


_HOST = socket.gethostname()
