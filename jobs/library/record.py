"""What a program has been through: its drip-feed runs per machine, and apart from them the
rollouts that sent it (a send puts a program on a machine; it does not run it)."""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from jobs.library.models import LibraryProgram
from jobs.models import Job, JobKind, Run, RunState, Target, TargetState

COUNTED = (RunState.SUCCEEDED, RunState.FAILED, RunState.STOPPED)  # ran, well or not


def runs_by_machine(*, session: Session, name: str) -> dict[str, dict[str, Any]]:
    """Per machine: runs that succeeded, that failed (a stop on request among them), the last."""
    found: dict[str, dict[str, Any]] = {}
    rows = session.execute(
        select(Run.machine_id, Run.state, Run.ended_at, Run.last_line)
        .where(Run.program_name == name, Run.state.in_(COUNTED))
        .order_by(Run.ended_at))
    for machine_id, state, ended_at, last_line in rows:
        entry = found.setdefault(machine_id, {"success": 0, "failure": 0, "last": None})
        ok = state is RunState.SUCCEEDED
        entry["success" if ok else "failure"] += 1
        entry["last"] = {"date": ended_at, "success": ok, "state": state.value,
                         "line": last_line}
    return found


def sends_by_machine(*, session: Session, program: LibraryProgram) -> dict[str, int]:
    """Per machine: how many send jobs delivered one of the program's versions."""
    version_ids = [v.id for v in program.versions]
    if not version_ids:
        return {}
    rows = session.execute(
        select(Target.machine_id, func.count()).join(Job, Job.id == Target.job_id)
        .where(Job.kind == JobKind.SEND, Job.library_version_id.in_(version_ids),
               Target.state == TargetState.SUCCEEDED)
        .group_by(Target.machine_id))
    return {machine_id: int(count) for machine_id, count in rows}
