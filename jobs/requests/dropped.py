"""The job a file found in a drop folder is recorded under, so that it is handled once.

The id is derived from the file: its machine, its path, its size, its modification time and
a digest of its bytes. A file seen again with its job recorded is one a worker handled and
was lost before it removed it: it is only removed. Once removed, its job is marked so; a
file just like it found after that (the operator dropped the same request again, perhaps
copied with its old modification time) is a new request, recorded under the next id.

The file's removal from the machine and the mark on its job cannot be one step, so the
removal is noted as under way first (per machine, in the data folder's
`requests/removing/`): a worker lost
between the two leaves the note, and the next whole look of the folder that no longer
finds the file marks the job.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select

from jobs.db import session_scope
from jobs.folders import private_dir, private_opener
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


def under_way(*, settings: Settings, machine_id: str) -> set[str]:
    """The jobs whose files' removal from the machine was begun and is not known done."""
    try:
        loaded = json.loads(_notes(settings, machine_id).read_text())
    except (FileNotFoundError, ValueError):
        return set()
    return {str(job_id) for job_id in loaded} if isinstance(loaded, list) else set()


def removing(*, settings: Settings, machine_id: str, job_id: str) -> None:
    """Note that the job's file is about to be removed from the machine."""
    _write_notes(settings, machine_id, under_way(settings=settings, machine_id=machine_id)
                 | {job_id})


def removed(*, settings: Settings, machine_id: str, job_id: str) -> None:
    """Mark the job's file as gone from the drop folder, and its removal as done."""
    gone(settings=settings, machine_id=machine_id, job_ids=[job_id])


def gone(*, settings: Settings, machine_id: str, job_ids: Iterable[str]) -> None:
    """Mark the jobs' files as gone: removed, or (removals a lost worker began) not found by
    a whole look of the folder made since.

    A job's file found again while its removal is under way is the one the lost worker did
    not remove, and is only removed; a copy of it dropped after the removal and before the
    next whole look would be taken for it alike.
    """
    done = set(job_ids)
    if not done:
        return
    with session_scope(settings.resolved_database_url) as session:
        for job in session.scalars(select(Job).where(Job.id.in_(done))):
            job.options = {**job.options, REMOVED: True}
    _write_notes(settings, machine_id,
                 under_way(settings=settings, machine_id=machine_id) - done)


def _notes(settings: Settings, machine_id: str) -> Path:
    return settings.data_dir / "requests" / "removing" / f"{machine_id}.json"


def _write_notes(settings: Settings, machine_id: str, job_ids: set[str]) -> None:
    """Write the notes whole, on the disk before the file is removed from the machine."""
    path = _notes(settings, machine_id)
    for level in (path.parent.parent, path.parent):  # each one 0700, made by the first write
        private_dir(level)
    temp = path.with_suffix(f".{os.getpid()}.tmp")
    with open(temp, "w", opener=private_opener) as out:
        out.write(json.dumps(sorted(job_ids)))
        out.flush()
        os.fsync(out.fileno())
    temp.replace(path)
