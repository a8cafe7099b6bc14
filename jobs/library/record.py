"""What a program has been through: its drip-feed runs per machine, and apart from them the
rollouts that sent it (a send puts a program on a machine; it does not run it)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from jobs.library.models import LibraryProgram
from jobs.models import Job, JobKind, Run, RunState, Target, TargetState

COUNTED = (RunState.SUCCEEDED, RunState.FAILED, RunState.STOPPED)  # ran, well or not


def runs_by_machine(*, session: Session, name: str) -> dict[str, dict[str, Any]]:
    """Per machine: the program's runs that succeeded, that failed (a stop on request among
    them), and the last one."""
    return _tally(session.execute(
        select(Run.machine_id, Run.state, Run.ended_at, Run.last_line)
        .where(Run.program_name == name, Run.state.in_(COUNTED)).order_by(Run.ended_at)))


def runs_by_program(*, session: Session, machine_id: str) -> dict[str, dict[str, Any]]:
    """Per program name: the machine's runs of it, counted as `runs_by_machine` does."""
    return _tally(session.execute(
        select(Run.program_name, Run.state, Run.ended_at, Run.last_line)
        .where(Run.machine_id == machine_id, Run.state.in_(COUNTED)).order_by(Run.ended_at)))


def _tally(rows: Iterable[Any]) -> dict[str, dict[str, Any]]:
    """(key, state, ended, line) rows in the order they ended, counted per key."""
    found: dict[str, dict[str, Any]] = {}
    for key, state, ended_at, last_line in rows:
        entry = found.setdefault(key, {"success": 0, "failure": 0, "last": None})
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
