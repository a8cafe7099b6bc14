"""A running target's own steps, outside the runners' shared transactions (jobs.run.targets):
its lease extended while its attempt works and the progress of a large transfer, each in a
transaction of its own; and, in the caller's (jobs.dnc.feeding.begin), the target put back to
wait when its attempt found the machine taken before it began.
"""

from __future__ import annotations

from sqlalchemy import update
from sqlalchemy.orm import Session

from jobs.db import session_scope
from jobs.models import Target, TargetState, utcnow
from jobs.run import leases


def put_back(*, session: Session, job_id: str, machine_id: str, attempt: int,
             status_msg: str) -> None:
    """The job's running target on the machine is pending again, its attempt neither counted
    nor recorded: the attempt found the machine taken before it began (a drip-feed run
    behind another, jobs.dnc.feeding.begin). Marked queued now: whoever frees the machine
    queues it, and the reaper looks again only after `redispatch_after_s`.

    Only while `attempt` is the one running, as a result settles (jobs.run.targets): a runner whose
    lease ran out, its target claimed again since, puts back nothing of the later claim.
    """
    session.execute(update(Target).where(
        Target.job_id == job_id, Target.machine_id == machine_id,
        Target.state == TargetState.RUNNING, Target.attempts == attempt)
        .values(state=TargetState.PENDING, attempts=Target.attempts - 1, lease_until=None,
                dispatched_at=utcnow(), status_msg=status_msg))


def extend_running(*, url: str, job_id: str, machine_id: str, lease_s: float) -> None:
    """Heartbeat: the job's running targets on the machine are still being worked on."""
    with session_scope(url) as session:
        session.execute(update(Target).where(
            Target.job_id == job_id, Target.machine_id == machine_id,
            Target.state == TargetState.RUNNING)
            .values(lease_until=leases.held_until(utcnow(), lease_s)))


def report_bytes(*, url: str, target_id: int, done: int, total: int | None) -> None:
    """Progress of a large transfer."""
    with session_scope(url) as session:
        session.execute(update(Target).where(Target.id == target_id)
                        .values(bytes_done=done, bytes_total=total))
