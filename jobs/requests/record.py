"""The job record of what a machine sent: a `request` job, one target per action.

The listener (or the drop-folder scan) holds the machine's lease while it answers, so the
targets are recorded running under it from the start and never go through the queue. If
that worker dies, the reaper puts them back like any target of a lost worker, and the
runner fails them: the control's moment to read the answer in has passed.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from sqlalchemy import insert, select
from sqlalchemy.orm import Session

from jobs import service
from jobs.db import session_scope
from jobs.errors import ContractError
from jobs.models import Job, JobKind, JobState, Target, TargetState, utcnow
from jobs.run import settle
from jobs.run.claims import worker_name
from jobs.settings import Settings

LISTENER_LOST = ("the worker answering this request was lost before it answered; ask "
                 "again from the control")


@dataclass(frozen=True)
class Opened:
    """A request job just recorded: its id and its targets' ids, in order."""

    job_id: str
    target_ids: list[int]


def open_job(*, settings: Settings, machine_id: str, file_name: str | None, received: bytes,
             steps: list[dict[str, Any]], created_by: str, job_id: str | None = None) -> Opened:
    """Record the job of one received program, its targets running under the caller's lease.

    Args:
        received: the text as it came in, kept with the job (its payload).
        steps: per target, what it does, as the job's view shows it (`action`, `folder`,
            `fileName`, `asked`, ...).
        job_id: the id the program was kept under (jobs.requests.spool); a new one if None.
    """
    with session_scope(settings.resolved_database_url) as session:
        return add_job(session=session, settings=settings, machine_id=machine_id,
                       file_name=file_name, received=received, steps=steps,
                       created_by=created_by, job_id=job_id)


def add_job(*, session: Session, settings: Settings, machine_id: str, file_name: str | None,
            received: bytes, steps: list[dict[str, Any]], created_by: str,
            job_id: str | None = None) -> Opened:
    """open_job in the caller's transaction, committed with what the caller adds to it."""
    now = utcnow()
    lease_until = now + timedelta(seconds=settings.lease_ttl_s)
    payload_id = service.store_payload(session=session, data=received)
    job = Job(id=job_id or uuid.uuid4().hex[:16], kind=JobKind.REQUEST, state=JobState.RUNNING,
              payload_id=payload_id, file_name=file_name, created_by=created_by[:100],
              options={}, created_at=now)
    session.add(job)
    session.flush()
    session.execute(insert(Target), [
        {"job_id": job.id, "position": i, "machine_id": machine_id, "params": step,
         "state": TargetState.RUNNING, "attempts": 1, "bytes_done": 0,
         "dispatched_at": now, "started_at": now, "lease_until": lease_until,
         "claimed_by": worker_name(), "interrupted": False}
        for i, step in enumerate(steps)])
    ids = list(session.scalars(select(Target.id).where(Target.job_id == job.id)
                               .order_by(Target.position)))
    return Opened(job.id, ids)


def recorded(*, settings: Settings, job_id: str) -> bool:
    """Whether the job of that id is recorded."""
    with session_scope(settings.resolved_database_url) as session:
        return session.scalar(select(Job.id).where(Job.id == job_id)) is not None


def finish(*, settings: Settings, target_id: int, error: ContractError | None = None,
           status_msg: str | None = None, state: TargetState | None = None,
           answer: tuple[str, bytes] | None = None) -> None:
    """Record one target's result, and what was sent back for it; settles the job."""
    with session_scope(settings.resolved_database_url) as session:
        finish_in(session=session, target_id=target_id, error=error, status_msg=status_msg,
                  state=state, answer=answer)


def finish_in(*, session: Session, target_id: int, error: ContractError | None = None,
              status_msg: str | None = None, state: TargetState | None = None,
              answer: tuple[str, bytes] | None = None) -> None:
    """finish in the caller's transaction."""
    target = session.get(Target, target_id)
    if target is None or target.state.final:
        return
    if answer is not None:
        name, data = answer
        target.params = {**target.params, "answer": name, "answerBytes": len(data),
                         "answerId": service.store_payload(session=session, data=data)}
    final = state or (TargetState.FAILED if error is not None else TargetState.SUCCEEDED)
    settle.finish_target(target, state=final, error=error, status_msg=status_msg)
    session.flush()
    settle.update_job_state(session=session, job_id=target.job_id)


def extend(*, settings: Settings, job_id: str) -> None:
    """Push the running targets' leases on while an answer waits for the control."""
    with session_scope(settings.resolved_database_url) as session:
        for target in session.scalars(select(Target).where(
                Target.job_id == job_id, Target.state == TargetState.RUNNING)):
            target.lease_until = utcnow() + timedelta(seconds=settings.lease_ttl_s)
