"""A target remembers an attempt that was cut off through the attempts after it.

An attempt cut off (its worker killed, its connection dropped) may have done its work: a
send may have got the file there, a delete may have removed it. The next attempt that finds
its own bytes there, or the file gone, counts as done. An attempt in between that found the
machine offline wrote nothing and proves nothing: the target must still know, or it ends
failed (142, 158) for work that was done.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import delete, update

from jobs import db, service
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.models import JobKind, MachineLease, Target, utcnow
from jobs.run import reaper, targets
from jobs.run.work import Work
from jobs.settings import Settings
from tests.jobs.helpers import on_each_database


@pytest.fixture(params=["postgresql", "sqlite"])
def settings(request: pytest.FixtureRequest, tmp_path: Path, settings: Settings) -> Settings:
    return on_each_database(request, tmp_path, settings)


def _job(settings: Settings, machine_id: str) -> str:
    """A delete job of one target on its own machine (the PostgreSQL server is the module's)."""
    with db.session_scope(settings.resolved_database_url) as session:
        registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
            {"id": machine_id, "name": "M", "model": "Mock"}), data_dir=settings.data_dir)
        return service.create(session=session, kind=JobKind.DELETE, targets=[
            service.TargetIn(machineID=machine_id, fileName="O1.NC")]).id


def _claimed(settings: Settings, job_id: str, machine_id: str) -> tuple[Work, str]:
    """The target claimed by a runner now (its retry delay waived)."""
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(Target).where(Target.job_id == job_id)
                        .values(next_attempt_at=None))
    started = targets.begin(settings=settings, job_id=job_id, machine_id=machine_id)
    assert started.work is not None and started.holder is not None
    return started.work, started.holder


def _failed(settings: Settings, work: Work, holder: str, code: ErrorCode) -> None:
    finished = targets.finish(settings=settings, work=work, holder=holder,
                              error=ContractError(code, "as the machine said"))
    assert finished.retry_in_s is not None  # the attempt is retried


def test_a_worker_lost_then_an_offline_machine_still_leaves_the_attempt_maybe_done(
        settings: Settings) -> None:
    job_id = _job(settings, "lost")
    work, holder = _claimed(settings, job_id, "lost")
    with db.session_scope(settings.resolved_database_url) as session:  # its worker dies
        session.execute(delete(MachineLease).where(MachineLease.holder == holder))
        session.execute(update(Target).where(Target.id == work.target_id)
                        .values(lease_until=utcnow()))
    reaper.reap(settings=settings)

    after_death, holder = _claimed(settings, job_id, "lost")
    _failed(settings, after_death, holder, ErrorCode.MACHINE_OFFLINE)
    after_offline, _ = _claimed(settings, job_id, "lost")

    assert after_death.may_have_written
    assert after_offline.attempt == 3 and after_offline.may_have_written


def test_a_dropped_connection_then_an_offline_machine_still_leaves_the_attempt_maybe_done(
        settings: Settings) -> None:
    job_id = _job(settings, "dropped")
    work, holder = _claimed(settings, job_id, "dropped")
    _failed(settings, work, holder, ErrorCode.CONNECTION_FAILED)
    work, holder = _claimed(settings, job_id, "dropped")
    _failed(settings, work, holder, ErrorCode.MACHINE_OFFLINE)

    after_offline, _ = _claimed(settings, job_id, "dropped")

    assert after_offline.attempt == 3 and after_offline.may_have_written


def test_attempts_that_found_the_machine_offline_alone_leave_nothing_maybe_done(
        settings: Settings) -> None:
    job_id = _job(settings, "offline")
    for _ in range(2):
        work, holder = _claimed(settings, job_id, "offline")
        _failed(settings, work, holder, ErrorCode.MACHINE_OFFLINE)

    third, _ = _claimed(settings, job_id, "offline")

    assert third.attempt == 3 and not third.may_have_written
