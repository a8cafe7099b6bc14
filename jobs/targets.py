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
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from jobs import leases, queue
from jobs.db import session_scope
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


def begin(*, settings: Settings, job_id: str, machine_id: str) -> Started:
    """In one transaction: the machine, a slot of it for the job, the job's first due target."""
    now = utcnow()
    with session_scope(settings.resolved_database_url) as session:
        machine = session.get(Machine, machine_id)
        if machine is None:
            return Started(None)
        spec = MachineSpec.of(machine)
        job = _job_info(session, job_id)
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
        session.execute(update(Job).where(Job.id == job_id, Job.state == JobState.QUEUED)
                        .values(state=JobState.RUNNING))
        return Started(spec, holder, work)


def _job_info(session: Session, job_id: str) -> JobInfo | None:
    row = session.execute(select(Job.kind, Job.options, Job.payload_id, Job.state)
                          .where(Job.id == job_id)).first()
    if row is None or row.state is JobState.CANCELLED:
        return None
    return JobInfo(job_id, row.kind, JobOptions(**row.options), row.payload_id)


def _claim(session: Session, job: JobInfo, machine_id: str, lease_s: float,
           now: datetime) -> Work | None:
    row = session.execute(
        select(Target.id, Target.params, Target.payload_id, Target.next_attempt_at,
               Target.interrupted)
        .where(Target.job_id == job.job_id, Target.machine_id == machine_id,
               Target.state == TargetState.PENDING)
        .order_by(Target.position).limit(1)).first()
    if row is None or (row.next_attempt_at and row.next_attempt_at > now):
        return None  # keep request order: a target waiting for its retry holds the rest
    number = session.scalar(
        update(Target).where(Target.id == row.id, Target.state == TargetState.PENDING)
        .values(state=TargetState.RUNNING, attempts=Target.attempts + 1, started_at=now,
                lease_until=now + timedelta(seconds=lease_s), claimed_by=worker_name())
        .returning(Target.attempts))
    if number is None:
        return None
    return Work(row.id, job, machine_id, dict(row.params), row.payload_id or job.payload_id,
                number, now, bool(row.interrupted))


def finish(*, settings: Settings, work: Work, holder: str, error: ContractError | None,
           state: TargetState = TargetState.SUCCEEDED, status_msg: str | None = None,
           replaced_payload_id: str | None = None) -> Finished:
    """Record the attempt, then claim the next due target or give the machine's slot back."""
    now = utcnow()
    retry_in = _retry_delay_s(settings, work, now) if (
        error is not None and error.code in TRANSIENT_CODES) else None
    with session_scope(settings.resolved_database_url) as session:
        session.add(Attempt(
            target_id=work.target_id, number=work.attempt, worker=worker_name(),
            started_at=work.started_at, finished_at=now,
            error_code=int(error.code) if error else 0,
            error_msg=(error.status_msg or str(error)) if error else None))
        values: dict[str, Any] = {"interrupted": False, "lease_until": None}
        if replaced_payload_id:
            values["replaced_payload_id"] = replaced_payload_id
        if retry_in is not None:
            assert error is not None
            values.update(
                state=TargetState.PENDING, next_attempt_at=now + timedelta(seconds=retry_in),
                dispatched_at=None, error_code=int(error.code),
                error_msg=error.body()["errorMsg"],
                status_msg=f"attempt {work.attempt} failed ({error.status_msg or ''}); "
                           f"retrying in {retry_in:.0f} s")
        else:
            body = error.body() if error else result(ErrorCode.SUCCESS, status_msg)
            values.update(state=TargetState.FAILED if error else state, finished_at=now,
                          next_attempt_at=None, error_code=body["errorCode"],
                          error_msg=body["errorMsg"], status_msg=body.get("statusMsg"))
        session.execute(update(Target).where(Target.id == work.target_id,
                                             Target.state == TargetState.RUNNING)
                        .values(**values))
        if error is not None and retry_in is None and work.options.abort_after_failures:
            _abort_if_too_many_failures(session, work.job.job_id,
                                        work.options.abort_after_failures)
        next_work = None
        if retry_in is None and _job_info(session, work.job.job_id) is not None:
            next_work = _claim(session, work.job, work.machine_id, settings.lease_ttl_s, now)
        waiting = None
        if next_work is None:
            leases.drop(session, holder=holder)
            waiting = _take_waiting(session, work.machine_id, now)
        update_job_state(session, work.job.job_id)
    return Finished(next_work, retry_in, waiting)


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
    session.execute(update(Target).where(
        Target.job_id == job_id, Target.machine_id == machine_id,
        Target.state == TargetState.PENDING).values(dispatched_at=None))


def _take_waiting(session: Session, machine_id: str, now: datetime) -> str | None:
    """The oldest job with due targets waiting for this machine, marked as queued."""
    job_id = session.scalar(
        select(Target.job_id).where(
            Target.machine_id == machine_id, Target.state == TargetState.PENDING,
            Target.dispatched_at.is_(None),
            (Target.next_attempt_at.is_(None)) | (Target.next_attempt_at <= now))
        .order_by(Target.job_id).limit(1))
    if job_id:
        session.execute(update(Target).where(
            Target.job_id == job_id, Target.machine_id == machine_id,
            Target.state == TargetState.PENDING).values(dispatched_at=now))
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
            moved = session.execute(
                update(Target).where(Target.id == target_id, Target.state == TargetState.RUNNING,
                                     Target.lease_until < now)
                .values(state=TargetState.PENDING, lease_until=None, dispatched_at=None,
                        interrupted=True, status_msg="its worker was lost; queued again")
            ).rowcount
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
    return len(groups)


def _has_free_slot(session: Session, machine_id: str, now: datetime) -> bool:
    limit = session.scalar(select(Machine.max_concurrent).where(Machine.id == machine_id)) or 1
    held = session.scalar(select(func.count()).where(
        MachineLease.machine_id == machine_id, MachineLease.expires_at >= now)) or 0
    return held < limit


def worker_name() -> str:
    """Who runs an attempt, for its record: host and process."""
    return f"{socket.gethostname()}:{os.getpid()}"
