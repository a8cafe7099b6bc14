"""The reaper: recovery from dead workers, a lost queue and races, by the database.

Every worker runs it (the embedded mode in-process) every `reaper_interval_s`. It never
waits for Redis's visibility timeout: the database knows which targets are running under
an expired lease and which pending ones nobody has queued lately.

A worker that dies takes with it the tasks it had received and not started (a gevent
worker holds twice its slots, and prefetches): once its lease shows it dead, the pending
targets queued before it died are queued again, without waiting `redispatch_after_s`.
A job committed whose tasks were never all sent (its API process died in between) stays
`queued`; after `UNQUEUED_AFTER_S` the reaper queues it.
"""

from __future__ import annotations

import os
import shutil
from datetime import datetime, timedelta

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from jobs import folders
from jobs.backup_models import Backup
from jobs.db import in_chunks, rowcount, session_scope
from jobs.models import (
    ACTIVE_STATES,
    Attempt,
    Job,
    JobKind,
    JobState,
    Machine,
    MachineLease,
    Run,
    RunState,
    Target,
    TargetState,
    state_is,
    utcnow,
)
from jobs.run import deliveries, job_ends, leases, queue
from jobs.run.outcomes import INTERRUPTED
from jobs.run.settle import update_job_state
from jobs.settings import Settings


def reap(*, settings: Settings) -> int:
    """Requeue what a dead worker or a lost queue left behind; returns the groups queued.

    Running targets whose lease expired go back to pending (their attempt is recorded
    as interrupted); pending, due targets not queued recently are queued again when
    their machine has a free slot.
    """
    now = utcnow()
    with session_scope(settings.resolved_database_url) as session:
        _keep_live_runs(session, settings, now)
        stale = session.execute(
            select(Target.id, Target.attempts, Target.started_at, Target.claimed_by,
                   Target.lease_until).where(
                state_is(TargetState.RUNNING), Target.lease_until < now)).all()
        redispatch_before = _redispatch_before(settings, now)
        for target_id, attempts, started_at, claimed_by, lease_until in stale:
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
                redispatch_before = max(redispatch_before, _died_by(settings, lease_until or now))
        _queue_unqueued_jobs(session, now)
        due = session.execute(
            select(Target.job_id, Target.machine_id).where(
                state_is(TargetState.PENDING),
                (Target.next_attempt_at.is_(None)) | (Target.next_attempt_at <= now),
                (Target.dispatched_at.is_(None)) | (Target.dispatched_at < redispatch_before))
            .distinct()).all()
        free = _with_free_slot(session, {m for _, m in due}, now)
        groups = [(j, m) for j, m in due if m in free]
        for job_id, machine_id in groups:
            session.execute(update(Target).where(
                Target.job_id == job_id, Target.machine_id == machine_id,
                Target.state == TargetState.PENDING).values(dispatched_at=now))
    queue.enqueue_machines(settings, groups)
    _settle_finished_jobs(settings)
    _assemble_forgotten_backups(settings, now)
    _remove_work_of_stored_backups(settings)
    return len(groups)


def _redispatch_before(settings: Settings, now: datetime) -> datetime:
    """Pending targets queued before this are taken for lost and queued again.

    `redispatch_after_s` ago, or, while this process is being delivered tasks queued
    earlier than now (a backlog draining), that long before the newest of them: the queue
    has not yet come to a target queued later, and queueing it again would only make a
    task that finds it done (jobs.run.deliveries).
    """
    window = timedelta(seconds=settings.redispatch_after_s)
    reached = deliveries.frontier(settings.redispatch_after_s)
    return min(now, reached or now) - window


UNQUEUED_AFTER_S = 5.0  # a job still `queued` this long after it was made lost its API
# A backup job ended this long ago without its ZIP has its assembly asked again: its own
# assembly, queued as its last target ended, has had the time to register it.
FORGOTTEN_AFTER_S = 2.0


def _keep_live_runs(session: Session, settings: Settings, now: datetime) -> None:
    """Drip-feed targets whose run was heard of within a lease period keep their lease.

    A run writes its record every few seconds while its link is up (worker.drip_run). A
    worker too busy to renew its leases in time is still feeding the machine: queueing
    the target again would start a second feed of the same program, so the run's own
    record, not the lease, says whether its worker lives.
    """
    heard_since = now - timedelta(seconds=settings.lease_ttl_s)
    live = (select(Target.id).join(Job, Job.id == Target.job_id)
            .join(Run, (Run.job_id == Target.job_id) & (Run.machine_id == Target.machine_id))
            .where(Job.kind == JobKind.DNC_RUN, Target.state == TargetState.RUNNING,
                   Target.lease_until < now, Run.state == RunState.RUNNING,
                   Run.updated_at >= heard_since))
    until = leases.held_until(now, settings.lease_ttl_s)
    kept = session.execute(select(Target.job_id, Target.machine_id).where(
        Target.id.in_(live))).all()
    for job_id, machine_id in kept:  # its machine stays its own too: no other work meanwhile
        session.execute(update(Target).where(Target.job_id == job_id,
                                             Target.machine_id == machine_id,
                                             Target.state == TargetState.RUNNING)
                        .values(lease_until=until))
        session.execute(update(MachineLease).where(MachineLease.machine_id == machine_id,
                                                   MachineLease.group == f"job:{job_id}")
                        .values(expires_at=until))


def _died_by(settings: Settings, lease_until: datetime) -> datetime:
    """When, at the latest, the worker whose target lease ran out at `lease_until` died.

    Its leases were pushed to HOLD_SHARE of a TTL ahead every RENEW_SHARE of one
    (jobs.run.leases); alive RENEW_SHARE of a TTL after its last push, it would have
    pushed this one further.
    """
    return lease_until - timedelta(
        seconds=settings.lease_ttl_s * (leases.HOLD_SHARE - leases.RENEW_SHARE))


def _queue_unqueued_jobs(session: Session, now: datetime) -> None:
    """Jobs made but never queued in full: their pending targets become due now.

    `jobs.service.dispatch` marks a job running only once every task is sent.
    """
    lost = session.scalars(select(Job.id).where(
        Job.state == JobState.QUEUED, Job.created_at < now - timedelta(seconds=UNQUEUED_AFTER_S))
        .with_for_update(skip_locked=True, key_share=True)).all()  # locked: being queued
    if not lost:
        return
    session.execute(update(Target).where(Target.job_id.in_(lost),
                                         Target.state == TargetState.PENDING)
                    .values(dispatched_at=None))
    session.execute(update(Job).where(Job.id.in_(lost)).values(state=JobState.RUNNING))


def _settle_finished_jobs(settings: Settings) -> None:
    """Jobs whose last targets finished at the same moment, each runner seeing the other
    still running, so that none settled the job: settle them now. A cancelled job is one
    of them until it is finished: its running targets were left to finish."""
    with session_scope(settings.resolved_database_url) as session:
        unsettled = session.scalars(select(Job.id).where(
            Job.state.in_([JobState.QUEUED, JobState.RUNNING])
            | ((Job.state == JobState.CANCELLED) & Job.finished_at.is_(None)),
            ~select(Target.id).where(Target.job_id == Job.id,
                                     Target.state.in_(ACTIVE_STATES)).exists())).all()
        for job_id in unsettled:
            update_job_state(session=session, job_id=job_id)
    for job_id in unsettled:  # committed: a request waiting for one may answer now
        job_ends.announce(settings, job_id)


_ASSEMBLY_ASKED: dict[str, datetime] = {}  # job -> when this process last queued its assembly


def _assemble_forgotten_backups(settings: Settings, now: datetime) -> None:
    """Backup jobs that finished without their ZIP (a worker died, a cancel ended them)."""
    settled = now - timedelta(seconds=FORGOTTEN_AFTER_S)
    with session_scope(settings.resolved_database_url) as session:
        finished = session.execute(select(Job.id, Job.options).where(
            Job.kind == JobKind.BACKUP, Job.finished_at.is_not(None), Job.finished_at < settled,
            Job.finished_at > now - timedelta(days=1),
            ~select(Backup.id).where(Backup.job_id == Job.id).exists())).all()
    # A ZIP is owed while the job's work folder exists (not after retention deleted it).
    # A streamed job owes none: what a target left after its download ended is removed.
    forgotten = []
    for job_id, options in finished:
        work = folders.job_folder(settings, job_id)
        if options.get("streamed"):
            if not folders.being_sent(work):  # a slow client still reads from it
                shutil.rmtree(work, ignore_errors=True)
        elif work.is_dir() and not options.get("unstored"):  # not when none could be written
            forgotten.append(job_id)
    for done in _ASSEMBLY_ASKED.keys() - set(forgotten):  # assembled, or older than a day
        del _ASSEMBLY_ASKED[done]
    for job_id in forgotten:
        asked = _ASSEMBLY_ASKED.get(job_id)
        if asked is not None and now - asked <= timedelta(minutes=5):
            continue  # asked lately: the backups folder is not read on every pass
        if folders.being_assembled(settings, job_id):
            continue  # a large backup's ZIP takes minutes: a second one beside it is waste
        _ASSEMBLY_ASKED[job_id] = now
        queue.enqueue_assembly(settings, job_id)


def _remove_work_of_stored_backups(settings: Settings) -> None:
    """The work folders of jobs whose ZIP is registered: an assembler killed between
    registering it and removing them leaves them, as large as the backup."""
    try:
        with os.scandir(folders.work_dir(settings)) as entries:
            job_ids = [entry.name for entry in entries if entry.is_dir()]
    except OSError:  # no backup was ever made here
        return
    if not job_ids:
        return
    with session_scope(settings.resolved_database_url) as session:
        stored = set(session.scalars(select(Backup.job_id).where(Backup.job_id.in_(job_ids))))
    for job_id in job_ids:
        if job_id in stored:
            shutil.rmtree(folders.job_folder(settings, job_id), ignore_errors=True)


def _with_free_slot(session: Session, machine_ids: set[str], now: datetime) -> set[str]:
    """Those of the machines that have a slot free (two queries per 10,000 machines)."""
    free = set[str]()
    for chunk in in_chunks(sorted(machine_ids)):  # a backlog of a 100,000-machine rollout
        limits = dict(session.execute(
            select(Machine.id, Machine.max_concurrent).where(Machine.id.in_(chunk))).all())
        held = dict(session.execute(
            select(MachineLease.machine_id, func.count()).where(
                MachineLease.machine_id.in_(chunk), MachineLease.expires_at >= now)
            .group_by(MachineLease.machine_id)).all())
        free.update(m for m in chunk if held.get(m, 0) < (limits.get(m) or 1))
    return free
