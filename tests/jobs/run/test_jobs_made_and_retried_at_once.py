"""A job's failed targets retried by two at the same moment run again once: the second retry
finds nothing failed and says so; a job made while its machine is removed fails that
target with 10003, as one made just before (on PostgreSQL and on SQLite)."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs import db, service
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.models import JobKind, Target, TargetState
from jobs.run import targets
from jobs.settings import Settings
from tests.jobs.helpers import on_each_database, one_delete_started, while_another_writes
from worker import runner


@pytest.fixture(params=["postgresql", "sqlite"])
def settings(request: pytest.FixtureRequest, tmp_path: Path, settings: Settings) -> Settings:
    return on_each_database(request, tmp_path, settings)


def _failed_once(settings: Settings) -> str:
    """A delete job with one target on one machine, its one attempt failed (158)."""
    job_id, started = one_delete_started(settings)
    targets.finish(settings=settings, work=started.work, holder=started.holder,
                   error=ContractError(ErrorCode.PATH_NOT_FOUND, "O1.NC"))
    return job_id


def test_two_retries_at_once_run_the_failed_target_again_once(settings: Settings) -> None:
    job_id = _failed_once(settings)

    def retried_meanwhile(session: Session) -> None:
        assert service.retry_failed(session=session, job_id=job_id) == 1

    def retry() -> int:
        with db.session_scope(settings.resolved_database_url) as session:
            return service.retry_failed(session=session, job_id=job_id)

    other = while_another_writes(settings.resolved_database_url, retried_meanwhile, retry)

    assert other == {"result": 0}  # nothing failed is left to retry
    again = targets.begin(settings=settings, job_id=job_id, machine_id="m1")
    assert again.work is not None
    targets.finish(settings=settings, work=again.work, holder=again.holder, error=None)
    assert targets.begin(settings=settings, job_id=job_id, machine_id="m1").work is None
    with db.session_scope(settings.resolved_database_url) as session:
        target = session.scalars(select(Target).where(Target.job_id == job_id)).one()
        assert (target.state, target.attempts) == (TargetState.SUCCEEDED, 2)


def test_a_job_made_while_its_machine_is_removed_fails_that_target_10003(
        settings: Settings) -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
            {"id": "m1", "name": "M1", "model": "Mock"}), data_dir=settings.data_dir)

    def made() -> str:
        with db.session_scope(settings.resolved_database_url) as session:
            return service.create(session=session, kind=JobKind.DELETE, targets=[
                service.TargetIn(machineID="m1", fileName="O1.NC")]).id

    other = while_another_writes(
        settings.resolved_database_url,
        lambda session: registry.delete(session=session, machine_id="m1"), made)

    job_id = other["result"]
    runner.run_machine(settings, job_id, "m1")  # as the task the job queued runs it
    with db.session_scope(settings.resolved_database_url) as session:
        target = session.scalars(select(Target).where(Target.job_id == job_id)).one()
        assert (target.state, target.error_code) == (TargetState.FAILED,
                                                     ErrorCode.MACHINE_NOT_FOUND)
