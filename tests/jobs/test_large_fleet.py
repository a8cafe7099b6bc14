"""A job over a fleet larger than one statement's parameters: PostgreSQL takes at most
65,535 of them, and a job of 100,000 targets must still be recorded whole."""

from __future__ import annotations

from sqlalchemy import func, insert, select

from jobs import db, service
from jobs.models import JobKind, Machine, Target, TargetState

FLEET = 70_000  # more ids than one statement may carry on PostgreSQL


def test_a_job_over_70000_machines_is_recorded_whole_in_order(postgres_url: str) -> None:
    ids = [f"big-{n:05d}" for n in range(FLEET)]
    with db.session_scope(postgres_url) as session:
        session.execute(insert(Machine), [
            {"id": m, "name": m, "model": "Mock", "transport": "mock"} for m in ids])
    targets = [service.TargetIn(machineID=m, fileName="A.NC") for m in ids]
    targets.insert(12_345, service.TargetIn(machineID="nobody", fileName="A.NC"))

    with db.session_scope(postgres_url) as session:
        job = service.create(session=session, kind=JobKind.SEND, targets=targets)
        job_id = job.id

    with db.session_scope(postgres_url) as session:
        states = dict(session.execute(select(Target.state, func.count()).where(
            Target.job_id == job_id).group_by(Target.state)).all())
        unknown = session.execute(select(Target.position, Target.error_code).where(
            Target.job_id == job_id, Target.state == TargetState.FAILED)).all()
    assert states == {TargetState.PENDING: FLEET, TargetState.FAILED: 1}
    assert [tuple(row) for row in unknown] == [(12_345, 10003)]
