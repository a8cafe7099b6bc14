"""What an attempt's end makes of its target and of its job, in the runners' shared
transaction (jobs.run.targets): the target's new row (retried after a backoff, cancelled
with its job, failed or done), a late report written into the reaper's record of it, a
machine gone meanwhile failing the job's targets there, a rollout stopped after too many
failures.
"""

from __future__ import annotations

import random
from datetime import datetime, timedelta
from typing import Any, cast

from sqlalchemy import Table, bindparam, func, select, update
from sqlalchemy.orm import Session

from jobs.db import rowcount
from jobs.errors import ErrorCode, disabled_machine, result, unknown_machine
from jobs.models import Attempt, Machine, Target, TargetState
from jobs.run.settle import cancel_pending, fail_pending
from jobs.run.work import MAY_HAVE_WRITTEN, Report, Work
from jobs.settings import Settings

INTERRUPTED = "interrupted: worker lost"
# The reaper's INTERRUPTED row of an attempt that had only stalled, once it ends after all:
# its result is not the target's, which the attempt after it gives.
LATE = "interrupted: its lease ran out and the target was queued again; the attempt then ended"

_ATTEMPTS, _M = (cast(Table, m.__table__) for m in (Attempt, Machine))
_ENDED_LATE = (update(_ATTEMPTS)
               .where(_ATTEMPTS.c.target_id == bindparam("target"),
                      _ATTEMPTS.c.number == bindparam("attempt"),
                      _ATTEMPTS.c.error_msg == INTERRUPTED)
               .values(finished_at=bindparam("done_at"), error_msg=bindparam("late_msg")))
# Whether each machine may still take targets (a finish with more to do asks only this).
_ENABLED = (select(_M.c.id, _M.c.enabled)
            .where(_M.c.id.in_(bindparam("machine_ids", expanding=True))))


def settlement(report: Report, retry_in: float | None, now: datetime, *,
                cancelled: bool = False) -> dict[str, Any]:
    """The target's new row values after the attempt; `cancelled`: its job was cancelled
    while this attempt, which would be retried, ran."""
    error, work = report.error, report.work
    settle: dict[str, Any] = {"replaced": report.replaced_payload_id,
                              "next_at": None, "done_at": now, "queued_at": now,
                              "cut_off": error is not None and error.code in MAY_HAVE_WRITTEN}
    if cancelled:
        assert error is not None
        body = result(ErrorCode.CANCELLED)
        settle.update(new_state=TargetState.CANCELLED, code=body["errorCode"],
                      msg=body["errorMsg"],
                      status=f"cancelled on request after attempt {work.attempt} failed "
                             f"({error.status_msg or error})")
    elif retry_in is not None:
        assert error is not None
        settle.update(
            new_state=TargetState.PENDING, next_at=now + timedelta(seconds=retry_in),
            done_at=None, queued_at=None, code=int(error.code), msg=error.body()["errorMsg"],
            status=f"attempt {work.attempt} failed ({error.status_msg or ''}); "
                   f"retrying in {retry_in:.0f} s")
    else:
        body = error.body() if error else result(ErrorCode.SUCCESS, report.status_msg)
        ended = TargetState.CANCELLED if error and error.code is ErrorCode.CANCELLED \
            else TargetState.FAILED  # a run stopped on request is cancelled, not failed
        settle.update(new_state=ended if error else report.state,
                      code=body["errorCode"], msg=body["errorMsg"],
                      status=body.get("statusMsg"))
    return settle


def retry_delay_s(settings: Settings, work: Work, now: datetime) -> float | None:
    """Seconds until the failed attempt's target is tried again; None when it is not (its
    tries or its window used up)."""
    tries = work.attempt - work.tries_before  # a retry on request counts from itself
    delay = min(settings.retry_max_s, settings.retry_base_s * 2 ** (tries - 1))
    delay *= random.uniform(0.5, 1.5)  # jitter: a fleet that failed together retries apart
    window = work.options.deliver_within
    if window is not None:  # tries until the window closes, or max_attempts if also given
        opened = work.counted_from or work.job.created_at
        remaining = (opened + timedelta(seconds=window) - now).total_seconds()
        given = work.options.max_attempts
        return min(delay, remaining) if remaining > 0 and (
            given is None or tries < given) else None
    max_attempts = work.options.max_attempts or settings.max_attempts
    return delay if tries < max_attempts else None


def record_late(session: Session, report: Report, now: datetime) -> bool:
    """Write what the stalled attempt did into the reaper's row of it; False if it has none
    (the target was not queued again but ended otherwise)."""
    error = report.error
    outcome = f"failed ({error.status_msg or error})" if error else report.state.value
    return rowcount(session.connection().execute(_ENDED_LATE, {
        "target": report.work.target_id, "attempt": report.work.attempt, "done_at": now,
        "late_msg": f"{LATE}: {outcome}"})) > 0


def still_usable(session: Session, reports: list[Report]) -> list[Report]:
    """The reports whose machine may take the job's next target.

    A machine disabled or removed while its targets ran takes no more: the job's pending
    targets there fail at once (20011, 10003) instead of being sent to it anyway.
    """
    if not reports:
        return []
    enabled = dict(session.connection().execute(
        _ENABLED, {"machine_ids": sorted({r.work.machine_id for r in reports})}).all())
    usable = []
    for r in reports:
        machine_id = r.work.machine_id
        if enabled.get(machine_id):
            usable.append(r)
            continue
        error = disabled_machine(machine_id) if machine_id in enabled else \
            unknown_machine(machine_id)
        fail_pending(session=session, job_id=r.work.job.job_id, machine_id=machine_id,
                     error=error)
    return usable


def abort_if_too_many_failures(session: Session, job_id: str, limit: int) -> None:
    """Cancel the job's pending targets once `limit` of its targets have failed."""
    # Counted one transaction at a time per job: failures recorded at the same moment by
    # two workers' transactions each counted only their own, and the rollout went past its
    # limit. An advisory lock of the job's, not its row: a rollout being queued holds the
    # row (jobs.service.dispatch), for seconds when it is large, and a failure meanwhile
    # held up every result of its worker's shared transaction until the queueing ended.
    conn = session.connection()
    if conn.dialect.name == "postgresql":  # SQLite: one writer at a time anyway
        conn.execute(select(func.pg_advisory_xact_lock(FAILURE_COUNT_LOCK,
                                                       func.hashtext(job_id))))
    failed = session.scalar(select(func.count()).where(
        Target.job_id == job_id, Target.state == TargetState.FAILED)) or 0
    if failed >= limit:  # targets failing together may take it past the limit: both named
        failures = "1 target" if failed == 1 else f"{failed} targets"
        cancel_pending(session=session, job_id=job_id,
                       status_msg=f"rollout aborted: {failures} failed (limit {limit})")


FAILURE_COUNT_LOCK = 0x646E6371  # "dncq": the class of the advisory locks taken above
