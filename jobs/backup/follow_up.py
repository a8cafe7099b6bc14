"""What follows a scheduled backup: its schedule's retention pass, and an alert on trouble.

A backup job a schedule started (a `ScheduleRun` names it) is followed up once its ZIP is
stored (`after_backup`) or could not be (`after_unstored`); `prune` also runs on its own
(`POST /api/schedules/prune`, `dncq backup prune`).
"""

from __future__ import annotations

import logging
from typing import Any
from zoneinfo import ZoneInfo

from sqlalchemy import select, update
from sqlalchemy.orm import Session, selectinload

from jobs import folders
from jobs import notify as alerts
from jobs.backup import manifests
from jobs.backup.retention import RetentionPolicy, to_prune
from jobs.backup_models import (
    Backup,
    BackupMachine,
    BackupStatus,
    MachineBackupStatus,
    Schedule,
    ScheduleRun,
)
from jobs.db import rowcount, session_scope
from jobs.fleet import sealed
from jobs.models import utcnow
from jobs.settings import Settings

log = logging.getLogger(__name__)


def after_backup(*, settings: Settings, backup_id: str) -> None:
    """A scheduled backup was stored: prune by the schedule's retention, alert on trouble.

    Done once, whichever delivery of its assembly asks: the first to mark the schedule's run
    does it, also one delivered again after a worker lost past the registration; one
    delivered beside it (the reaper asks again for an assembly that takes seconds) finds the
    run marked and does nothing. A worker lost between the mark and the alert loses the
    alert: a second alert for every slow assembly would be worse.
    """
    url = settings.resolved_database_url
    with session_scope(url) as session:
        backup = session.get(Backup, backup_id)
        if backup is None:
            return
        marked = rowcount(session.execute(update(ScheduleRun).where(
            ScheduleRun.job_id == backup.job_id, ScheduleRun.followed_up_at.is_(None))
            .values(followed_up_at=utcnow())))
        if marked != 1:  # no schedule started it, or another delivery took the steps
            return
        schedule = _schedule_of(session, backup.job_id)
        status, name = backup.status, backup.name
        urls = alert_urls(settings, schedule)
        why = manifests.failure_details(session=session, job_id=backup.job_id)
        failed = [f"{m.machine_id}: {m.error_code} {m.error_msg}" + _detail(why, m)
                  for m in backup.machines if m.status is not MachineBackupStatus.OK]
    if schedule is not None and schedule.retention:
        try:
            prune(settings=settings, schedule_name=schedule.name)
        except Exception:  # the next run prunes again; the alert below must not wait for it
            log.exception("schedule %s: the retention pass after backup %s failed",
                          schedule.name, name)
    if schedule is not None and status is not BackupStatus.COMPLETE and urls:
        _alert(urls, title=f"dncq: backup {schedule.name} is {status.value}",
               body=f"{name}: {len(failed)} machine(s) not backed up:\n" + "\n".join(failed),
               details={"backup": backup_id, "status": status.value, "failed": failed})


def _detail(why: dict[str, str], machine: BackupMachine) -> str:
    said = why.get(machine.machine_id)
    return f" - {said}" if said and said != machine.error_msg else ""


def after_unstored(*, settings: Settings, job_id: str, reason: str) -> None:
    """A scheduled backup's ZIP could not be written (jobs.backup.store): alert as for a
    failed backup."""
    with session_scope(settings.resolved_database_url) as session:
        schedule = _schedule_of(session, job_id)
        urls = alert_urls(settings, schedule)
    if schedule is not None and urls:
        _alert(urls, title=f"dncq: backup {schedule.name} is {BackupStatus.FAILED.value}",
               body=f"job {job_id}: the backup could not be stored: {reason}",
               details={"job": job_id, "status": BackupStatus.FAILED.value,
                        "failed": [reason]})


def _schedule_of(session: Session, job_id: str | None) -> Schedule | None:
    """The schedule that started the job, if one did (and still exists)."""
    run = session.scalars(select(ScheduleRun).where(ScheduleRun.job_id == job_id)).first()
    return session.get(Schedule, run.schedule_name) if run else None


def _alert(urls: list[str], **message: Any) -> None:
    for problem in alerts.notify(urls=urls, **message):
        log.warning("alert not delivered: %s", problem)


def prune(*, settings: Settings, schedule_name: str | None = None,
          dry_run: bool = False) -> list[str]:
    """Delete backups their schedule's retention no longer keeps; returns their names."""

    pruned: list[str] = []
    with session_scope(settings.resolved_database_url) as session:
        query = select(Schedule)
        if schedule_name:
            query = query.where(Schedule.name == schedule_name)
        for schedule in session.scalars(query):
            if not schedule.retention:
                continue
            policy = RetentionPolicy.parse(schedule.retention)
            backups = list(session.scalars(select(Backup).join(
                ScheduleRun, ScheduleRun.job_id == Backup.job_id).where(
                ScheduleRun.schedule_name == schedule.name).options(
                selectinload(Backup.machines))))  # each machine's last copies are kept
            doomed = _doomed(backups, policy, ZoneInfo(schedule.timezone))
            for backup in backups:
                if backup.id in doomed:
                    pruned.append(backup.name)
                    if not dry_run:
                        session.delete(backup)
    # The ZIPs go once their rows are gone: a database lost at the commit leaves a file no
    # backup lists, not a listed backup without its file.
    for name in [] if dry_run else pruned:
        try:
            (folders.backup_dir(settings) / name).unlink(missing_ok=True)
        except OSError as exc:
            log.warning("pruned backup %s: its ZIP could not be removed: %s", name, exc)
    return sorted(pruned)


def _doomed(backups: list[Backup], policy: RetentionPolicy, tz: ZoneInfo) -> set[str]:
    """The backups the policy drops. A failed backup (no machine backed up) never takes the
    place of one that holds files: the policy picks among those that do, and a failed one
    is dropped as soon as the policy over them all would drop it. Counted together, two
    nights with the fleet offline pruned its last usable backups under `last=2`. Each
    machine's last copies stay whatever the policy says (`_last_copies`)."""
    usable = [(b.id, b.created_at) for b in backups if b.status is not BackupStatus.FAILED]
    failed = {b.id for b in backups if b.status is BackupStatus.FAILED}
    everything = [(b.id, b.created_at) for b in backups]
    doomed = to_prune(usable, policy, tz=tz) | (failed & to_prune(everything, policy, tz=tz))
    return doomed - _last_copies(backups)


def _last_copies(backups: list[Backup]) -> set[str]:
    """For each machine of the newest backup, the newest backup that holds all its files
    and the newest that holds any: a machine off for a few nights makes partial backups
    that the policy keeps, and its only good copy is in an older one."""
    newest_first = sorted(backups, key=lambda b: b.created_at, reverse=True)
    if not newest_first:
        return set()
    machines = {m.machine_id for m in newest_first[0].machines}  # the schedule's, now
    kept: dict[tuple[str, bool], str] = {}  # (machine, whole) -> backup
    for backup in newest_first:
        for m in backup.machines:
            if m.machine_id in machines and m.status is not MachineBackupStatus.FAILED:
                kept.setdefault((m.machine_id, False), backup.id)
                if m.status is MachineBackupStatus.OK:
                    kept.setdefault((m.machine_id, True), backup.id)
    return set(kept.values())


def alert_urls(settings: Settings, schedule: Schedule | None) -> list[str]:
    """Where a schedule's trouble is told: the global URLs and the schedule's own (stored
    sealed; left out, and said in the log, when this host's keys cannot unseal them)."""
    own: list[str] = []
    if schedule is not None and schedule.notify:
        try:
            keys = sealed.keyring(settings.data_dir, create=False)
            own = [keys.unseal(url) for url in schedule.notify]
        except sealed.SecretsKeyError as exc:
            log.error("the alert URLs of schedule %s cannot be read, so it is told only to "
                      "the global ones: %s", schedule.name, exc)
    return [*settings.notify_urls, *own]
