"""Drip-feed runs as the API, the CLI and the dashboard read them: a job's runs, the runs
filtered, one run's view, and which running ones have gone silent (the health report's).

Read only: a run is started, moved and ended by jobs.dnc.runs and its runner.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs.models import Run, RunState, utcnow


def of_job(*, session: Session, job_id: str) -> list[Run]:
    """The job's runs, in the order of its targets."""
    return list(session.scalars(select(Run).where(Run.job_id == job_id)
                                .order_by(Run.position)))


def list_runs(*, session: Session, machine_id: str | None = None, program: str | None = None,
              state: RunState | None = None, since: datetime | None = None,
              until: datetime | None = None, limit: int = 100) -> list[Run]:
    """Runs, newest first, filtered."""
    query = select(Run).order_by(Run.created_at.desc(), Run.id.desc()).limit(limit)
    if machine_id:
        query = query.where(Run.machine_id == machine_id)
    if program:
        query = query.where(Run.program_name == program)
    if state:
        query = query.where(Run.state == state)
    if since:
        query = query.where(Run.created_at >= since)
    if until:
        query = query.where(Run.created_at < until)
    return list(session.scalars(query))


SILENT_AFTER_S = 15.0  # a running run not heard of for this long: its link or worker is in trouble


def silent_s(run: Run) -> float | None:
    """Seconds since a running run was last heard of, when that is too long; else None."""
    if run.state is not RunState.RUNNING:
        return None
    quiet = (utcnow() - run.updated_at).total_seconds()
    return round(quiet, 1) if quiet > SILENT_AFTER_S else None


def link_report(*, session: Session) -> dict[str, Any]:
    """The health report's view of the runs: how many run, and which are silent."""
    running = list(session.scalars(select(Run).where(Run.state == RunState.RUNNING)))
    silent = [{"run": r.id, "jobId": r.job_id, "machineID": r.machine_id, "line": r.last_line,
               "silentS": silent_s(r)} for r in running if silent_s(r) is not None]
    return {"running": len(running), "silent": silent}


def view(run: Run) -> dict[str, Any]:
    """A run as the API shows it."""
    return {
        "id": run.id, "jobId": run.job_id, "machineID": run.machine_id,
        "program": run.program_name, "programId": run.program_id, "state": run.state.value,
        "startedBy": run.started_by, "createdAt": run.created_at,
        "startedAt": run.started_at, "endedAt": run.ended_at,
        "line": run.last_line, "linesTotal": run.lines_total, "linesSent": run.lines_sent,
        "startLine": run.start_line, "restartFrom": run.restart_from,
        "headerLines": len(run.header or []), "stopRequested": run.stop_requested,
        "stoppedBy": run.stopped_by,
        "message": run.message, "updatedAt": run.updated_at, "silentS": silent_s(run),
    }
