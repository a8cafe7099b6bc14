"""2.6.13 backupFiles: the ZIP streamed while the workers fetch its backup job.

The route checks every target first (`streamed.check`), so those errors come back as the
contract's JSON, then makes a backup job marked `streamed`. The workers fetch its targets
as they fetch a stored backup's: one task per machine under the machine's lease,
deflating as they read, transient faults retried. No ZIP is assembled for it: this
module streams one from their work files, machine after machine in the request's order,
each as soon as its targets are fetched, and only copies bytes.

A target that fails, or a wait of `batch_wait_s` with none of the job's targets running,
aborts the download (the client never sees a ZIP that looks whole); the job then records
the failure, and what was fetched as cancelled, since the client has none of it.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import select, update

from jobs.backup import archive_names, store
from jobs.backup.streamed import MachinePlan
from jobs.backup.zipwriter import PreparedMember, deflated, joined, write_zip
from jobs.backup_models import MachineBackupStatus
from jobs.db import held, session_scope
from jobs.errors import MESSAGES, ContractError, ErrorCode
from jobs.folders import job_folder, sending
from jobs.models import ACTIVE_STATES, Job, JobState, Target, TargetState
from jobs.run import settle
from jobs.settings import Settings

log = logging.getLogger(__name__)

SENT_BYTES = 256 * 1024  # the ZIP goes out in pieces of about this size
POLL_S = 0.01  # how often the download looks whether the machine it waits for is fetched
ABORTED = "the download ended before it was whole"


def stream(*, settings: Settings, job_id: str, plans: list[MachinePlan],
           now: datetime | None = None) -> Iterator[bytes]:
    """The ZIP: `BackupFiles_<date>/<id>_<name>/...` and the manifest, streamed."""
    top = archive_names.backup_name(now or datetime.now()) + "/"
    made = datetime.now(UTC)
    with session_scope(settings.resolved_database_url) as session:
        rows = session.execute(select(Target.machine_id, Target.id).where(
            Target.job_id == job_id).order_by(Target.position)).all()
    targets_of: dict[str, list[int]] = {}
    for machine_id, target_id in rows:
        targets_of.setdefault(machine_id, []).append(target_id)
    fetched = _Fetched(settings, job_id)

    def members() -> Iterator[PreparedMember]:
        yield PreparedMember(top, made)
        entries: list[dict[str, Any]] = []
        folders = archive_names.machine_folders([(p.spec.id, p.spec.name) for p in plans])
        for plan, machine_folder in zip(plans, folders, strict=True):
            target_ids = targets_of[plan.spec.id]
            fetched.wait_for(plan.spec.id, target_ids)  # a failure here aborts the download
            folder = top + machine_folder + "/"
            entry: dict[str, Any] = {
                "machineID": plan.spec.id, "machineName": plan.spec.name,
                "status": MachineBackupStatus.OK, "errorMsg": None, "leftOut": [], "files": []}
            entries.append(entry)
            yield PreparedMember(folder, made)
            seen: set[str] = set()
            for target_id in target_ids:
                yield from store.target_members(store.work_file(settings, job_id, target_id),
                                                folder, entry, seen, made)
        manifest = {"created": made.isoformat(), "job": job_id,
                    "machines": [store.machine_manifest(entry) for entry in entries]}
        yield deflated(top + archive_names.MANIFEST_NAME, datetime.now(UTC),
                       json.dumps(manifest, indent=1).encode(), level=settings.backup_zip_level)

    complete = False
    # The job ends with its last target, long before a slow client has the ZIP: the reaper
    # leaves a streamed job's work files alone while this reads them.
    with sending(job_folder(settings, job_id)):
        try:
            yield from joined(write_zip(members()), SENT_BYTES)
            complete = True
        except BaseException as exc:
            if not isinstance(exc, Exception):  # failures are logged where the answer is cut
                log.warning("backup download ended before it was whole (the client went away)")
            raise
        finally:
            if not complete:
                _abort(settings, job_id)
            # A target still running leaves its work file later; the reaper removes it.
            shutil.rmtree(job_folder(settings, job_id), ignore_errors=True)


class _Fetched:
    """Waits for a machine's targets to be fetched, and for the job to make progress."""

    def __init__(self, settings: Settings, job_id: str) -> None:
        self.url, self.job_id = settings.resolved_database_url, job_id
        self.patience_s = settings.batch_wait_s
        self.progress_at = time.monotonic()

    def wait_for(self, machine_id: str, target_ids: list[int]) -> None:
        """Return once every one of the targets succeeded; raise the first one's error
        (in request order) that did not, or when none of the job's targets ran for
        `batch_wait_s` (no worker takes them)."""
        left = set(target_ids)
        while True:
            with session_scope(self.url) as session:
                done = session.execute(select(
                    Target.id, Target.state, Target.error_code, Target.error_msg).where(
                    Target.id.in_(left), Target.state.not_in(ACTIVE_STATES))).all()
                running = not done and session.scalar(select(Target.id).where(
                    Target.job_id == self.job_id, Target.state == TargetState.RUNNING
                ).limit(1)) is not None
            failed = [row for row in done if row.state is not TargetState.SUCCEEDED]
            if failed:
                first = min(failed, key=lambda row: target_ids.index(row.id))
                raise ContractError(_code(first.error_code),
                                    f"{first.error_msg or first.state.value} ({machine_id})")
            left -= {row.id for row in done}
            if done or running:
                self.progress_at = time.monotonic()
            if not left:
                return
            if time.monotonic() - self.progress_at > self.patience_s:
                raise ContractError(ErrorCode.MACHINE_TIMEOUT, (
                    f"none of the backup's targets ran for {self.patience_s:g} s "
                    f"(is a worker running?); {machine_id} was not fetched"))
            time.sleep(POLL_S)


def _code(error_code: int | None) -> ErrorCode:
    if error_code is None:
        return ErrorCode.INTERNAL_ERROR
    try:
        return ErrorCode(error_code)
    except ValueError:
        return ErrorCode.INTERNAL_ERROR


def _abort(settings: Settings, job_id: str) -> None:
    """Record a download that ended before it was whole: the targets not yet started and
    those already fetched end cancelled, the one that failed stays failed; a target still
    running finishes, but is not retried."""
    try:
        with session_scope(settings.resolved_database_url) as session:
            # held first, as a cancel holds it (jobs.run.targets._cancelled_jobs), on SQLite
            # too (FOR UPDATE takes no lock there)
            job = session.scalar(held(session, select(Job).where(Job.id == job_id)))
            assert job is not None
            settle.cancel_pending(session=session, job_id=job_id, status_msg=ABORTED)
            # fetched, but the client has none of it
            session.execute(update(Target).where(
                Target.job_id == job_id, Target.state == TargetState.SUCCEEDED).values(
                state=TargetState.CANCELLED, error_code=int(ErrorCode.CANCELLED),
                error_msg=MESSAGES[ErrorCode.CANCELLED], status_msg=ABORTED))
            failed = session.scalar(select(Target.id).where(
                Target.job_id == job_id, Target.state == TargetState.FAILED).limit(1))
            # Cancelled unless a failure ended it; a target still running is not retried.
            if failed is None or not settle.is_finished(session=session, job_id=job_id):
                job.state = JobState.CANCELLED
            settle.update_job_state(session=session, job_id=job_id)
    except Exception:  # the client's answer is already cut; a lost record must not hide it
        log.exception("recording the aborted backup download %s failed", job_id)
