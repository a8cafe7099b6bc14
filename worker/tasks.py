"""Celery tasks: thin, they take ids and call the runner."""

from __future__ import annotations

from celery import shared_task

from jobs.run.queue import ASSEMBLE_BACKUP, RUN_MACHINE, SCHEDULE_TICK
from jobs.settings import Settings


@shared_task(name=RUN_MACHINE, bind=True, acks_late=True)
def run_machine(self, job_id: str, machine_id: str) -> None:  # type: ignore[no-untyped-def]
    """Run one job's targets on one machine."""
    from worker.runner import run_machine as run

    settings: Settings = self.app.conf.dncq_settings
    run(settings, job_id, machine_id)


@shared_task(name=ASSEMBLE_BACKUP, bind=True, acks_late=True)
def assemble_backup(self, job_id: str) -> None:  # type: ignore[no-untyped-def]
    """Write a finished backup job's ZIP, register it, then prune and alert by its schedule."""
    from jobs.backup import follow_up, store
    from jobs.errors import ContractError
    from jobs.run import job_ends

    settings: Settings = self.app.conf.dncq_settings
    try:
        backup_id = store.assemble(settings=settings, job_id=job_id)
    except ContractError as exc:  # no ZIP can be written (a full disk): the job says why
        job_ends.announce(settings, job_id)
        follow_up.after_unstored(settings=settings, job_id=job_id,
                                 reason=exc.status_msg or str(exc))
        return
    if backup_id is not None:  # a client may be waiting for the ZIP (GET /api/backups?wait_s=)
        job_ends.announce(settings, job_id)
        # Also when an earlier delivery, or another beside this one, registered it: the
        # schedule's steps are done once, by whichever asks first (after_backup).
        follow_up.after_backup(settings=settings, backup_id=backup_id)


@shared_task(name=SCHEDULE_TICK, ignore_result=True)
def schedule_tick() -> None:
    """Start the backups whose schedule is due (sent by Celery beat)."""
    from celery import current_app

    from jobs import schedules

    schedules.tick(settings=current_app.conf.dncq_settings)
