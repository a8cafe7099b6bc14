"""The job a file found in a drop folder is recorded under, so that it is handled once.

The id is derived from the file: its machine, its path, its size, its modification time and
a digest of its bytes. A file seen again with its job recorded is one a worker handled and
was lost before it removed it: it is only removed. Once removed, its job is marked so; a
file just like it found after that (the operator dropped the same request again, perhaps
copied with its old modification time) is a new request, recorded under the next id.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

from sqlalchemy import select

from jobs.db import session_scope
from jobs.models import Job
from jobs.settings import Settings

REMOVED = "dropped_file_removed"  # in the job's options (JobOptions): its file left the folder


@dataclass(frozen=True)
class DroppedJob:
    """The job of one dropped file: its id, and whether it is recorded already."""

    id: str
    recorded: bool  # handled by a worker lost before it removed the file: only remove it


def job_for(*, settings: Settings, machine_id: str, path: str, size: int | None,
            mtime: float | None, data: bytes) -> DroppedJob:
    """The job that records the dropped file `path` of the machine, as it is now."""
    same_file = json.dumps([machine_id, path, size, mtime,
                            hashlib.sha256(data).hexdigest()]).encode()
    generation = 0
    with session_scope(settings.resolved_database_url) as session:
        while True:
            job_id = hashlib.sha256(same_file + b"#%d" % generation).hexdigest()[:16]
            options = session.scalar(select(Job.options).where(Job.id == job_id))
            if options is None:
                return DroppedJob(job_id, recorded=False)
            if not options.get(REMOVED):
                return DroppedJob(job_id, recorded=True)
            generation += 1  # that one was removed: this is the same request dropped again


def removed(*, settings: Settings, job_id: str) -> None:
    """Mark the job's file as gone from the drop folder.

    A worker lost between the removal and this mark leaves a file dropped again just like
    it (same bytes, same modification time) to be taken for the handled one and removed
    unhandled; the other order would run a handled request twice.
    """
    with session_scope(settings.resolved_database_url) as session:
        job = session.get(Job, job_id)
        if job is not None:
            job.options = {**job.options, REMOVED: True}
