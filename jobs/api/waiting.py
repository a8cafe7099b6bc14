"""Requests that answer once a job has got somewhere: its end, or its backup's ZIP.

The database says whether it has; between looks the request listens for the job's end
said on Redis (jobs.run.job_ends), which cuts the pause short.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from fastapi.concurrency import run_in_threadpool
from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs.backup_models import Backup
from jobs.db import session_scope
from jobs.folders import job_folder
from jobs.models import Job, JobKind, utcnow
from jobs.run import job_ends
from jobs.settings import Settings

POLL_MAX_S = 0.1  # how late a waiting request may notice an end nobody said
POLL_MIN_S = 0.005
POLL_SHARE = 0.05  # without Redis, an end is noticed within this share of the job's age
WAIT_MAX_S = 60.0  # the longest a client may ask a read to wait (`wait_s`)


async def until(settings: Settings, job_id: str, timeout_s: float,
                reached: Callable[..., bool]) -> bool:
    """Wait until `reached(session=, job_id=)` holds or `timeout_s` passed; whether it holds.

    An end said on Redis ends the pause at once, so a runner's last result is answered
    without waiting for the next look; the looks, one indexed query each, catch an end
    whose message was lost, ten times a second. Without Redis (the embedded
    queue, or Redis down) they are all there is: about 70 in a job's first second and 10 a
    second from its third on, counted from the job's creation, so that a client asking
    again and again for a long job does not start over at the quick looks.
    """
    url = settings.resolved_database_url
    deadline = time.monotonic() + timeout_s

    def look() -> bool:
        with session_scope(url) as session:
            return reached(session=session, job_id=job_id)

    def age_s() -> float:
        with session_scope(url) as session:
            created = session.scalar(select(Job.created_at).where(Job.id == job_id))
        return max((utcnow() - created).total_seconds(), 0.0) if created else 0.0

    async with job_ends.listening(settings, job_id) as listener:
        if await run_in_threadpool(look):
            return True
        born: float | None = None  # the job's creation on this clock, asked once if needed
        while True:
            left_s = deadline - time.monotonic()
            if left_s <= 0:
                return False
            if listener.live:  # only an end whose message was lost is left to look for
                pause_s = POLL_MAX_S
            else:
                if born is None:
                    born = time.monotonic() - await run_in_threadpool(age_s)
                pause_s = min(max((time.monotonic() - born) * POLL_SHARE, POLL_MIN_S),
                              POLL_MAX_S)
            await listener.wait(min(pause_s, left_s))
            if await run_in_threadpool(look):
                return True


def backup_made(*, settings: Settings, session: Session, job_id: str) -> bool:
    """The backup job's ZIP is registered, or none will be: no backup job has that id, or
    the job ended owing none (the ZIP could not be written: the job says so, and its work
    folder is gone where it could be removed)."""
    if session.scalar(select(Backup.id).where(Backup.job_id == job_id).limit(1)) is not None:
        return True
    job = session.execute(select(Job.kind, Job.finished_at, Job.options)
                          .where(Job.id == job_id)).first()
    if job is None or job.kind is not JobKind.BACKUP:
        return True
    return job.finished_at is not None and (
        bool(job.options.get("unstored")) or not job_folder(settings, job_id).is_dir())
