"""Jobs: create, fan out, record, retry, cancel.

A job's targets are grouped by machine and one `dncq.run_machine` task per group
runs them in request order (worker.runner). Every state change is a conditional
update, so a target that reached a final state is never run again, whoever asks. Job and
target state is written here, by the runners (jobs.run.targets, jobs.run.outcomes,
jobs.run.running), by the reaper (jobs.run.reaper)
and, for a streamed backupFiles, by jobs.backup.streamed. How a job is shown is
jobs.job_views.
"""

from __future__ import annotations

import hashlib
import logging
import uuid
from collections.abc import Iterable
from datetime import datetime, timedelta
from typing import Any, cast

from pydantic import BaseModel, ConfigDict, Field, ValidationError
from sqlalchemy import Table, select, update
from sqlalchemy.orm import Session

from jobs.db import IN_CHUNK, in_chunks, insert_rows, rowcount, session_scope, upsert_of
from jobs.errors import (
    ContractError,
    ErrorCode,
    unknown_machine,
    validation_summary,
)
from jobs.job_options import JobOptions
from jobs.job_views import none_begun
from jobs.models import (
    Job,
    JobKind,
    JobState,
    Machine,
    Payload,
    Target,
    TargetState,
    utcnow,
)
from jobs.run import queue
from jobs.run.settle import cancel_pending, counts, update_job_state
from jobs.settings import Settings

log = logging.getLogger(__name__)

def own_spelling(raw: dict[str, Any], names: Iterable[str]) -> dict[str, Any]:
    """`raw` with its keys that are one of `names` in another case (`DirAtCNC`, `Content`,
    as a client's classes may write them) named so; one also given as named wins."""
    by_key = {name.lower(): name for name in names}
    fields = dict(raw)
    for other in list(fields):
        name = by_key.get(other.lower())
        if name and name != other:
            value = fields.pop(other)
            fields.setdefault(name, value)
    return fields


def target_fields(raw: dict[str, Any]) -> dict[str, Any]:
    """A target's fields under one spelling, for batch and backup targets alike.

    The contract writes both `dirAtCNC` and `DirAtCNC` (and so on); any case is taken, and
    `dirAtCNC` wins when both are given. A numeric machineID or fileName becomes its string.
    """
    fields = own_spelling(raw, ("machineID", "fileName", "dirAtCNC", "subDir", "includeSubDir"))
    for name in ("machineID", "fileName"):  # 1010, or a Fanuc program's number 8000
        if isinstance(fields.get(name), int) and not isinstance(fields[name], bool):
            fields[name] = str(fields[name])
    return fields


class TargetIn(BaseModel):
    """One target as the contract writes it; `DirAtCNC`/`SubDir` spellings accepted too."""

    model_config = ConfigDict(extra="ignore", populate_by_name=True)

    machineID: str = ""
    fileName: str | None = None
    dirAtCNC: str | None = None
    subDir: str | None = None
    includeSubDir: bool | None = None  # backup targets: folders below too (default true)
    archivePath: str | None = None  # restore targets: the file in the backup ZIP
    problem: str | None = Field(default=None, exclude=True)  # why the target is unusable

    @classmethod
    def parse(cls, raw: Any) -> TargetIn:
        """A target from a request body, accepting the contract's two spellings.

        A malformed target becomes one that fails at its own position, not the request.
        """
        if not isinstance(raw, dict):
            return cls(problem="a target is an object with machineID")
        try:
            return cls._parse(raw)
        except ValidationError as exc:
            return cls(machineID=str(raw.get("machineID", "")),
                       problem=validation_summary(exc.errors(), whole="target"))

    @classmethod
    def _parse(cls, raw: dict[str, Any]) -> TargetIn:
        fields = target_fields(raw)
        fields.pop("archivePath", None)  # dncq's own, set by a restore only
        return cls.model_validate(fields)

    def params(self) -> dict[str, Any]:
        """What a runner needs besides the machine."""
        return {k: v for k, v in (("fileName", self.fileName), ("dirAtCNC", self.dirAtCNC),
                                  ("subDir", self.subDir), ("includeSubDir", self.includeSubDir),
                                  ("archivePath", self.archivePath))
                if v is not None}


def payload_data(*, session: Session, payload_id: str) -> bytes | None:
    """The bytes kept as `payload_id`, None when there is no such payload (or it was
    pruned, no job using it)."""
    return session.scalar(select(Payload.data).where(Payload.id == payload_id))


def store_payload(*, session: Session, data: bytes) -> str:
    """Keep `data` once in the database; returns its id (the SHA-256).

    Two requests that send the same program at the same moment both find it missing; the
    second's insert then waits for the first's and does nothing, where a plain insert
    failed it on the key.
    """
    digest = hashlib.sha256(data).hexdigest()
    # Held (FOR KEY SHARE) until the job that uses it is committed: `prune` skips it.
    if session.scalar(select(Payload.id).where(Payload.id == digest)
                      .with_for_update(read=True, key_share=True)) is None:
        session.execute(upsert_of(session)(Payload).values(
            id=digest, size=len(data), data=data).on_conflict_do_nothing())
    return digest


def _registered(session: Session, machine_ids: set[str]) -> set[str]:
    """Which of the ids are registered machines, asked in chunks (a fleet of 100,000)."""
    known = set[str]()
    for chunk in in_chunks(sorted(machine_ids)):
        known.update(session.scalars(select(Machine.id).where(Machine.id.in_(chunk))))
    return known


def create(*, session: Session, kind: JobKind, targets: list[TargetIn],
           options: JobOptions | None = None, payload_id: str | None = None,
           target_payloads: dict[int, str | ContractError] | None = None,
           file_name: str | None = None, created_by: str = "api") -> Job:
    """Record a job and its targets; targets that cannot run fail at once (10003, 20001).

    Args:
        target_payloads: per position, a payload other than the job's (content written
            in each machine's own encoding), or the error that made one impossible.
    """
    job = Job(id=uuid.uuid4().hex[:16], kind=kind, payload_id=payload_id, created_by=created_by,
              file_name=file_name,
              options=(options or JobOptions()).model_dump(exclude_defaults=True))
    session.add(job)
    session.flush()
    known = _registered(session, {t.machineID for t in targets})
    now, own = utcnow(), target_payloads or {}
    # Rows are made and sent IN_CHUNK at a time: a 100,000-target job's rows at once took
    # the API process past 500 MB.
    for start in range(0, len(targets), IN_CHUNK):
        insert_rows(session, _TARGETS, [
            _target_row(job.id, position, t, known, own.get(position), now)
            for position, t in enumerate(targets[start:start + IN_CHUNK], start)])
    update_job_state(session=session, job_id=job.id)
    return job


_TARGETS = cast(Table, Target.__table__)


def _target_row(job_id: str, position: int, t: TargetIn, known: set[str],
                own: str | ContractError | None, now: datetime) -> dict[str, Any]:
    """A target's row: pending, or failed at once at its own position (10003, 20001)."""
    error = None
    if t.problem or not t.machineID:
        error = ContractError(ErrorCode.BAD_PARAMETER, t.problem or "machineID is required")
    elif t.machineID not in known:
        error = unknown_machine(t.machineID)
    elif isinstance(own, ContractError):
        error = own
    row: dict[str, Any] = {
        "job_id": job_id, "position": position, "machine_id": t.machineID,
        "params": t.params(), "payload_id": own if isinstance(own, str) else None,
        "state": TargetState.PENDING, "attempts": 0, "bytes_done": 0,
        "dispatched_at": now, "interrupted": False}
    if error is not None:
        body = error.body()
        row.update(state=TargetState.FAILED, finished_at=now, error_code=body["errorCode"],
                   error_msg=body["errorMsg"], status_msg=body.get("statusMsg"))
    return row


def dispatch(*, settings: Settings, job_id: str, fresh: bool = False) -> int:
    """Queue one task per machine that has pending targets in the job; returns the count.

    The job's row is held (PostgreSQL) until every task is sent: a reaper takes a job still
    `queued` for one whose API was lost, and skips a row it cannot lock, so that queueing a
    job of 100,000 targets, which takes longer than the reaper waits, is not done twice.

    `fresh`: the job was created just now and its targets already carry a queue time, the
    moment `create` recorded them, which the reaper's `redispatch_after_s` (60 s) counts
    from. They are not stamped again: for 500 targets that update took 9 ms before the
    first task could be sent. (A job whose creation took seconds is taken for queued that
    much early.)

    A broker that cannot be reached leaves the job recorded and `queued`, which the reaper
    queues again once the broker answers: the request that made it must not be told it
    failed (a client that tried again would send, replace or delete twice).
    """
    url = settings.resolved_database_url
    with session_scope(url) as held:
        if held.get_bind().dialect.name != "sqlite":  # SQLite: one writer at a time anyway
            held.execute(select(Job.id).where(Job.id == job_id)
                         .with_for_update(key_share=True))
        pending = (Target.job_id == job_id, Target.state == TargetState.PENDING)
        with session_scope(url) as session:
            machine_ids = list(session.scalars(select(Target.machine_id).where(*pending)
                                               .distinct()))
            if not fresh:
                session.execute(update(Target).where(*pending).values(dispatched_at=utcnow()))
        try:
            queue.enqueue_machines(settings, [(job_id, machine_id) for machine_id in machine_ids])
        except queue.BROKER_FAILURES as exc:
            log.warning("job %s recorded but not queued: the broker did not answer (%s); the "
                        "reaper queues it once it does", job_id, type(exc).__name__,
                        extra={"job_id": job_id})
            return len(machine_ids)
        if machine_ids:  # every task sent: a job left `queued` is one the reaper queues again
            held.execute(update(Job).where(Job.id == job_id, Job.state == JobState.QUEUED)
                         .values(state=JobState.RUNNING))
    return len(machine_ids)


# -- reading ---------------------------------------------------------------------------


def get_job(*, session: Session, job_id: str, for_update: bool = False) -> Job:
    """The job, or a 404-worthy ContractError; `for_update`: its row held until the commit
    (before any of its targets is touched: see jobs.run.targets._cancelled_jobs)."""
    job = session.get(Job, job_id, with_for_update=for_update, populate_existing=for_update)
    if job is None:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no job {job_id}")
    return job


def list_jobs(*, session: Session, state: JobState | None = None, kind: JobKind | None = None,
              machine_id: str | None = None, since: datetime | None = None,
              until: datetime | None = None, limit: int = 100) -> list[Job]:
    """Jobs, newest first, filtered."""
    query = select(Job).order_by(Job.created_at.desc()).limit(limit)
    if state is JobState.QUEUED:  # as `view` shows them
        query = query.where((Job.state == state)
                            | ((Job.state == JobState.RUNNING) & none_begun(Job.id)))
    elif state is JobState.RUNNING:
        query = query.where(Job.state == state, ~none_begun(Job.id))
    elif state:
        query = query.where(Job.state == state)
    if kind:
        query = query.where(Job.kind == kind)
    if since:
        query = query.where(Job.created_at >= since)
    if until:
        query = query.where(Job.created_at < until)
    if machine_id:
        query = query.where(Job.id.in_(select(Target.job_id)
                                       .where(Target.machine_id == machine_id)))
    return list(session.scalars(query))


# -- asking for more -----------------------------------------------------------------


def retry_failed(*, session: Session, job_id: str) -> int:
    """Put the job's failed and cancelled targets back in the queue; history is kept."""
    job = get_job(session=session, job_id=job_id, for_update=True)  # as a cancel holds it
    if job.options.get("streamed"):
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            "a streamed backup went to its client and cannot be retried; "
                            "start a backup job instead")
    if job.kind is JobKind.DNC_RUN:  # from the top again would cut what is already cut
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            "a drip-feed run is not retried: start a new run, restarted "
                            "where the machine stopped (dncq run MACHINE FILE --from-line N)")
    if job.kind is JobKind.REQUEST:  # the control waited for its answer then, not now
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            "a request from a machine is answered when the operator sends it; "
                            "it is asked again from the control")
    if job.kind is JobKind.BACKUP:  # its ZIP is made once; a retry would not change it
        failed = sorted({t.machine_id for t in job.targets if t.state in (
            TargetState.FAILED, TargetState.CANCELLED)})
        again = f": dncq backup run --to {','.join(failed)}" if failed else ""
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            f"a backup job's ZIP is made once; back up the machines that "
                            f"failed in a new backup{again}")
    n = rowcount(session.execute(
        update(Target).where(Target.job_id == job.id,
                             Target.state.in_([TargetState.FAILED, TargetState.CANCELLED]),
                             Target.error_code != ErrorCode.MACHINE_NOT_FOUND,
                             # refused when the job was made (a bad parameter): again would be
                             ~((Target.state == TargetState.FAILED) & (Target.attempts == 0)))
        .values(state=TargetState.PENDING, next_attempt_at=None, finished_at=None,
                dispatched_at=None, status_msg=None,
                # its tries count from here, as a new job's would (Target.retried_after)
                retried_after=Target.attempts, retried_at=utcnow())
    ))
    if n:
        job.state, job.finished_at = JobState.RUNNING, None
    return int(n)


def cancel(*, session: Session, job_id: str, status_msg: str = "cancelled on request") -> int:
    """Cancel the targets not yet started, saying `status_msg`; running ones finish.
    Returns how many."""
    job = get_job(session=session, job_id=job_id, for_update=True)
    n = cancel_pending(session=session, job_id=job.id, status_msg=status_msg)
    if job.finished_at is None:  # running targets finish; the job stays cancelled
        job.state = JobState.CANCELLED
    update_job_state(session=session, job_id=job.id)  # finished now if none runs
    return int(n)


def prune(*, session: Session, older_than: timedelta) -> int:
    """Delete finished jobs older than `older_than` and payloads no job uses any more.

    Rows held by a request at that moment are left for the next prune: a job being retried
    or cancelled (they hold its row), a payload a job being made is to use (`store_payload`
    holds it). Taken, they would be deleted under that request.
    """
    cutoff = utcnow() - older_than
    old = list(session.scalars(select(Job).where(Job.finished_at.is_not(None),
                                                 Job.finished_at < cutoff)
                               .with_for_update(skip_locked=True)))
    for job in old:
        session.delete(job)
    session.flush()
    used = set(session.scalars(select(Job.payload_id).where(Job.payload_id.is_not(None))))
    used |= set(session.scalars(select(Target.payload_id).where(Target.payload_id.is_not(None))))
    used |= set(session.scalars(select(Target.replaced_payload_id)
                                .where(Target.replaced_payload_id.is_not(None))))
    for payload in session.scalars(select(Payload).where(Payload.id.not_in(used or {""}))
                                   .with_for_update(skip_locked=True)):
        session.delete(payload)
    return len(old)


def alert_if_failed(*, settings: Settings, job_id: str) -> None:
    """Tell the configured alert URLs about a finished rollout with failed targets."""
    if not settings.notify_urls:
        return
    from jobs import notify

    with session_scope(settings.resolved_database_url) as session:
        job = get_job(session=session, job_id=job_id)
        c = counts(session=session, job_id=job_id)
        failed = [f"{t.machine_id}: {t.error_code} {t.error_msg}" for t in job.targets
                  if t.state in (TargetState.FAILED, TargetState.CANCELLED)]
        kind = job.kind.value
    if failed:
        notify.notify(urls=settings.notify_urls,
                      title=f"dncq: {kind} job {job_id} has {len(failed)} failed targets",
                      body="\n".join(failed[:50]), details={"job": job_id, "counts": c})
