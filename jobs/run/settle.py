"""A job's end states: finish a target, fail or cancel the pending ones, settle the job.

Used by the runners' shared transactions (jobs.run.targets), the reaper, the streamed
backupFiles and jobs.service; every update is conditional, so a target that reached a final
state keeps it, whoever asks.
"""

from __future__ import annotations

from sqlalchemy import case, func, select, update
from sqlalchemy.orm import Session

from jobs.db import rowcount
from jobs.errors import MESSAGES, ContractError, ErrorCode, result
from jobs.models import ACTIVE_STATES, Job, JobState, Target, TargetState, utcnow

INTERRUPTED_MAY_HAVE_DONE_IT = ("an attempt cut off (its worker lost, or its connection) may "
                                "have got through")


def counts(*, session: Session, job_id: str) -> dict[str, int]:
    """How many targets are in each state."""
    rows = session.execute(select(Target.state, func.count()).where(Target.job_id == job_id)
                           .group_by(Target.state))
    found = {state.value: n for state, n in rows}
    return {s.value: found.get(s.value, 0) for s in TargetState}


def is_finished(*, session: Session, job_id: str) -> bool:
    """Every target of the job is final."""
    return session.scalar(select(Target.id).where(
        Target.job_id == job_id, Target.state.in_(ACTIVE_STATES)).limit(1)) is None


def cancel_pending(*, session: Session, job_id: str, status_msg: str) -> int:
    """Cancel the job's targets not yet started (20015); returns how many.

    A target waiting to run again after its worker died says that the attempt cut off may
    have got through: the machine may hold what the cancelled target was to do.
    """
    said = case((Target.interrupted, f"{status_msg}; {INTERRUPTED_MAY_HAVE_DONE_IT}"),
                else_=status_msg)
    return rowcount(session.execute(
        update(Target).where(Target.job_id == job_id, Target.state == TargetState.PENDING)
        .values(state=TargetState.CANCELLED, error_code=int(ErrorCode.CANCELLED),
                error_msg=MESSAGES[ErrorCode.CANCELLED], status_msg=said,
                finished_at=utcnow())))


def finish_target(target: Target, *, state: TargetState, error: ContractError | None,
                  status_msg: str | None = None) -> None:
    """Give a target its final state and result."""
    target.state, target.finished_at = state, utcnow()
    target.next_attempt_at, target.lease_until = None, None
    body = error.body() if error else result(ErrorCode.SUCCESS, status_msg)
    target.error_code, target.error_msg = body["errorCode"], body["errorMsg"]
    target.status_msg = body.get("statusMsg")


def fail_pending(*, session: Session, job_id: str, machine_id: str,
                 error: ContractError) -> None:
    """Fail the job's pending targets on one machine at once (it left the registry)."""
    for target in session.scalars(select(Target).where(
            Target.job_id == job_id, Target.machine_id == machine_id,
            Target.state == TargetState.PENDING)):
        finish_target(target, state=TargetState.FAILED, error=error)
    session.flush()
    update_job_state(session=session, job_id=job_id)


def update_job_state(*, session: Session, job_id: str) -> bool:
    """Settle the job's state once no target is pending or running; whether it is."""
    if not is_finished(session=session, job_id=job_id):
        return False
    c = counts(session=session, job_id=job_id)
    ok = c["succeeded"] + c["skipped"] == sum(c.values())
    # Conditional, as one statement: a cancel committed while this transaction ran (one
    # that found every target running, and cancelled none) is not overwritten; read first
    # and written after, the job's state was its snapshot's, and the job ended succeeded.
    # "fetch": the session's own copy of the job takes what the row now holds.
    session.execute(update(Job).where(Job.id == job_id, Job.state != JobState.CANCELLED)
                    .values(state=JobState.SUCCEEDED if ok else JobState.FAILED)
                    .execution_options(synchronize_session="fetch"))
    session.execute(update(Job).where(Job.id == job_id, Job.finished_at.is_(None))
                    .values(finished_at=utcnow()).execution_options(synchronize_session="fetch"))
    return True
