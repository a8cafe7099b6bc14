"""A runner's claim of a target: the first due one of each (job, machine) made running
under the runner's lease, its attempt counted and signed by the worker, as the work to do.

Run in the shared transactions of jobs.run.targets, for a batch of runners at once.
"""

from __future__ import annotations

import os
import socket
from datetime import datetime
from typing import cast

from sqlalchemy import Table, bindparam, func, select, tuple_, update
from sqlalchemy.orm import Session

from jobs.models import Target, TargetState
from jobs.run import deliveries, leases
from jobs.run.work import JobInfo, Work

# Statements of the hot path, built once (see jobs.run.targets).
_T = cast(Table, Target.__table__)
# The first pending target of each (job, machine) in the batch; the caller keeps the pairs
# it asked for. A target waiting for its retry holds the later ones back (request order).
_FIRST_PENDING = (
    select(_T.c.job_id, _T.c.machine_id, func.min(_T.c.position), func.count())
    .where(_T.c.job_id.in_(bindparam("job_ids", expanding=True)),
           _T.c.machine_id.in_(bindparam("machine_ids", expanding=True)),
           _T.c.state == TargetState.PENDING)
    .group_by(_T.c.job_id, _T.c.machine_id))
_CLAIM = (
    update(_T)
    .where(tuple_(_T.c.job_id, _T.c.position).in_(bindparam("keys", expanding=True)),
           _T.c.state == TargetState.PENDING,
           _T.c.next_attempt_at.is_(None) | (_T.c.next_attempt_at <= bindparam("now")))
    .values(state=TargetState.RUNNING, attempts=_T.c.attempts + 1,
            started_at=bindparam("now"), lease_until=bindparam("until"),
            claimed_by=bindparam("worker"))
    .returning(_T.c.id, _T.c.job_id, _T.c.machine_id, _T.c.params, _T.c.payload_id,
               _T.c.attempts, _T.c.interrupted, _T.c.error_code, _T.c.dispatched_at,
               _T.c.retried_after, _T.c.retried_at))


def claim_many(session: Session, jobs: dict[str, JobInfo], pairs: list[tuple[str, str]],
               lease_s: float, now: datetime, *, delivered: bool = False
               ) -> dict[tuple[str, str], Work]:
    """Claim the first due target of each (job, machine); those with none are left out.

    `delivered`: the claims are of tasks the queue just delivered (not a runner's next
    target), whose queue times tell the reaper how far the queue has got.
    """
    if not pairs:
        return {}
    conn = session.connection()
    wanted = set(pairs)
    firsts = conn.execute(_FIRST_PENDING, {"job_ids": sorted({j for j, _ in pairs}),
                                           "machine_ids": sorted({m for _, m in pairs})})
    pending = {(job_id, machine_id): (position, count)
               for job_id, machine_id, position, count in firsts
               if (job_id, machine_id) in wanted}
    if not pending:
        return {}
    rows = conn.execute(_CLAIM, {"keys": [(job_id, position) for (job_id, _), (position, _)
                                          in pending.items()],
                                 "now": now, "worker": worker_name(),
                                 "until": leases.held_until(now, lease_s)}).all()
    if delivered:
        for row in rows:
            deliveries.note(row.dispatched_at)
    return {(row.job_id, row.machine_id): Work(
        row.id, jobs[row.job_id], row.machine_id, dict(row.params),
        row.payload_id or jobs[row.job_id].payload_id, row.attempts, now, bool(row.interrupted),
        more=pending[row.job_id, row.machine_id][1] > 1, previous_error=row.error_code,
        tries_before=row.retried_after or 0, counted_from=row.retried_at)
        for row in rows}


def worker_name() -> str:
    """Who runs an attempt, for its record: host and process."""
    return f"{_HOST}:{os.getpid()}"


_HOST = socket.gethostname()
