"""Where dncq keeps stored backups under its data folder, and a backup job's work folder.

On the ground floor because the job, the runners, the reaper and the schedules all need
them, not only the backup package.
"""

from __future__ import annotations

from pathlib import Path

from jobs.settings import Settings


def backup_dir(settings: Settings) -> Path:
    """Where stored backups live."""
    return settings.data_dir / "backups"


def job_folder(settings: Settings, job_id: str) -> Path:
    """The job's work folder: made with the job, removed once its ZIP is registered.

    While it exists the job owes a ZIP; a job whose backup retention has since deleted
    has none, so the reaper does not assemble it again.
    """
    return backup_dir(settings) / ".work" / job_id
