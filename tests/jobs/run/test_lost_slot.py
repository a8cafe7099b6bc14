"""A runner that stalled past its lease and lost the machine's slot takes no more targets.

A worker stopped (SIGSTOP, swapped out, starved of CPU) for longer than a lease loses its
slot: the lease expires, another taker clears it and takes the slot, and the reaper gives
the stalled attempt's target to another runner. When the stalled worker wakes, its
operation ends and is recorded; it must not then claim the job's next target on that
machine, which would give a machine of `max_concurrent: 1` two operations at once for the
rest of the job. On PostgreSQL and SQLite, as the runners' shared transaction runs on both.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import delete, select

from jobs import db, service
from jobs.fleet import registry
from jobs.models import JobKind, MachineLease, Target, TargetState
from jobs.run import leases, targets
from jobs.settings import Settings
from tests.jobs.helpers import on_each_database


@pytest.fixture(params=["postgresql", "sqlite"])
def settings(request: pytest.FixtureRequest, tmp_path: Path, settings: Settings) -> Settings:
    return on_each_database(request, tmp_path, settings)


def _started(settings: Settings, machine_id: str) -> tuple[str, targets.Started]:
    """A delete job of three targets on one machine (each test its own: the PostgreSQL
    server is the module's), its first claimed by a runner."""
    with db.session_scope(settings.resolved_database_url) as session:
        registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
            {"id": machine_id, "name": "M", "model": "Mock"}), data_dir=settings.data_dir)
        job_id = service.create(session=session, kind=JobKind.DELETE, targets=[
            service.TargetIn(machineID=machine_id, fileName=f"O{n}.NC") for n in (1, 2, 3)]).id
    started = targets.begin(settings=settings, job_id=job_id, machine_id=machine_id)
    assert started.work is not None and started.holder is not None
    return job_id, started


def _states(settings: Settings, job_id: str) -> list[TargetState]:
    with db.session_scope(settings.resolved_database_url) as session:
        return list(session.scalars(select(Target.state).where(Target.job_id == job_id)
                                    .order_by(Target.position)))


def test_a_runner_that_kept_its_slot_goes_on_to_the_next_target(settings: Settings) -> None:
    job_id, started = _started(settings, "kept")
    assert started.work is not None and started.holder is not None

    finished = targets.finish(settings=settings, work=started.work, holder=started.holder,
                              error=None)

    assert finished.next_work is not None and finished.next_work.params["fileName"] == "O2.NC"
    assert _states(settings, job_id) == [TargetState.SUCCEEDED, TargetState.RUNNING,
                                         TargetState.PENDING]


def test_a_runner_that_lost_its_slot_while_stalled_takes_no_next_target(
        settings: Settings) -> None:
    job_id, started = _started(settings, "lost")
    assert started.work is not None and started.holder is not None
    url = settings.resolved_database_url
    with db.session_scope(url) as session:  # its lease ran out and was cleared...
        session.execute(delete(MachineLease).where(MachineLease.holder == started.holder))
    other = leases.acquire(url, machine_id="lost", max_concurrent=1, group=f"job:{job_id}")
    assert other is not None  # ...and the slot went to another runner of the job

    finished = targets.finish(settings=settings, work=started.work, holder=started.holder,
                              error=None)

    assert finished.next_work is None
    assert _states(settings, job_id) == [TargetState.SUCCEEDED, TargetState.PENDING,
                                         TargetState.PENDING]
    with db.session_scope(url) as session:  # the slot stays the other runner's
        assert session.scalars(select(MachineLease.holder).where(
            MachineLease.machine_id == "lost")).all() == [other]
