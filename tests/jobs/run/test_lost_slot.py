"""A runner that stalled past its lease and lost the machine's slot takes no more targets.

A worker stopped (SIGSTOP, swapped out, starved of CPU) for longer than a lease loses its
slot: the lease expires, another taker clears it and takes the slot, and the reaper gives
the stalled attempt's target to another runner. When the stalled worker wakes, its
operation ends and is recorded; it must not then claim the job's next target on that
machine, which would give a machine of `max_concurrent: 1` two operations at once for the
rest of the job; nor settle its target, which the other runner's attempt now runs. On
PostgreSQL and SQLite, as the runners' shared transaction runs on both.
"""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import delete, select, update

from jobs import db, service
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.models import Attempt, JobKind, MachineLease, Target, TargetState, utcnow
from jobs.run import leases, reaper, targets
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


def _run_again(settings: Settings, job_id: str, started: targets.Started) -> targets.Started:
    """The first runner stalled past its leases: the reaper queues its target again, and a
    second runner of the job takes the slot and begins that target's next attempt."""
    assert started.work is not None
    url = settings.resolved_database_url
    with db.session_scope(url) as session:
        ran_out = utcnow() - timedelta(seconds=1)
        session.execute(update(Target).where(Target.id == started.work.target_id)
                        .values(lease_until=ran_out))
        session.execute(update(MachineLease).where(MachineLease.holder == started.holder)
                        .values(expires_at=ran_out))
    reaper.reap(settings=settings)
    again = targets.begin(settings=settings, job_id=job_id, machine_id=started.work.machine_id)
    assert again.work is not None and again.work.target_id == started.work.target_id
    assert again.work.attempt == 2
    return again


def _history(settings: Settings, target_id: int) -> list[tuple[int, int | None, str | None]]:
    with db.session_scope(settings.resolved_database_url) as session:
        return [(a.number, a.error_code, a.error_msg) for a in session.scalars(
            select(Attempt).where(Attempt.target_id == target_id).order_by(Attempt.id))]


def test_a_stalled_attempt_that_ends_after_its_target_ran_again_leaves_it_to_that_attempt(
        settings: Settings) -> None:
    job_id, stalled = _started(settings, "late")
    again = _run_again(settings, job_id, stalled)
    assert stalled.work is not None and stalled.holder is not None
    assert again.work is not None and again.holder is not None

    late = targets.finish(settings=settings, work=stalled.work, holder=stalled.holder,
                          error=None)

    assert late.next_work is None and not late.job_done
    assert _states(settings, job_id) == [TargetState.RUNNING, TargetState.PENDING,
                                         TargetState.PENDING]
    finished = targets.finish(settings=settings, work=again.work, holder=again.holder,
                              error=None)
    assert finished.next_work is not None and finished.next_work.params["fileName"] == "O2.NC"
    assert _states(settings, job_id)[0] is TargetState.SUCCEEDED
    history = _history(settings, again.work.target_id)
    assert [(number, code) for number, code, _ in history] == [(1, None), (2, 0)]
    assert history[0][2] == ("interrupted: its lease ran out and the target was queued "
                             "again; the attempt then ended: succeeded")


def test_a_stalled_attempt_that_fails_after_its_target_ran_again_asks_no_retry(
        settings: Settings) -> None:
    job_id, stalled = _started(settings, "late-failed")
    again = _run_again(settings, job_id, stalled)
    assert stalled.work is not None and stalled.holder is not None

    late = targets.finish(settings=settings, work=stalled.work, holder=stalled.holder,
                          error=ContractError(ErrorCode.MACHINE_TIMEOUT, "no answer in 10 s"))

    assert late.retry_in_s is None and late.next_work is None
    assert _states(settings, job_id) == [TargetState.RUNNING, TargetState.PENDING,
                                         TargetState.PENDING]
    with db.session_scope(settings.resolved_database_url) as session:  # still the slot's
        assert session.scalars(select(MachineLease.holder).where(
            MachineLease.machine_id == "late-failed")).all() == [again.holder]
