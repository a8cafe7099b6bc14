"""Slots taken outside the jobs (jobs.run.slot) hand their machines on when given back: a
batch that found a machine busy meanwhile, and waits for it, is queued then."""

from __future__ import annotations

from typing import Any

import pytest
from sqlalchemy import select, update

from jobs import db, service
from jobs.fleet import registry
from jobs.models import JobKind, Target
from jobs.run import slot
from jobs.settings import Settings


def _waiting_job(settings: Settings, add_machines: Any) -> str:
    """A delete job on machine m1 whose target found the machine busy: not queued."""
    add_machines({"id": "m1", "name": "M", "model": "Mock"})
    with db.session_scope(settings.resolved_database_url) as session:
        job_id = service.create(session=session, kind=JobKind.DELETE,
                                targets=[service.TargetIn(machineID="m1", fileName="a.nc")]).id
        session.execute(update(Target).where(Target.job_id == job_id)
                        .values(dispatched_at=None))
    return job_id


def _queued(settings: Settings, job_id: str) -> bool:
    with db.session_scope(settings.resolved_database_url) as session:
        return session.scalar(select(Target.dispatched_at)
                              .where(Target.job_id == job_id)) is not None


@pytest.mark.parametrize("fails", [False, True])
def test_slots_taken_together_hand_their_machines_on_however_the_work_ended(
        settings: Settings, add_machines: Any, fails: bool) -> None:
    job_id = _waiting_job(settings, add_machines)
    with db.session_scope(settings.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id="m1")

    class Broke(Exception):
        pass

    try:
        with slot.free_slots(settings, [spec]) as held:
            assert held == {"m1"}
            assert not _queued(settings, job_id)  # the machine is held: the batch waits
            if fails:
                raise Broke
    except Broke:
        pass
    assert _queued(settings, job_id)
