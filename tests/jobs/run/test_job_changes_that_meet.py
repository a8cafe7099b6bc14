"""Changes to one job that meet: a cancel and a failed attempt's result being recorded,
a cancel and a retry of the job's failed targets, two failures that reach a rollout's
`abort_after_failures` together, a prune and a retry or a job being made.

The attempt would be retried; the cancel finds its target running and leaves it to finish.
Whichever of the two transactions commits first, the target must end cancelled and the
job finished, and the job's end must be said, so that a batch request waiting for it
answers. A retry the cancel meets is cancelled with the rest; failures recorded at once
are counted together; a prune leaves what another request holds. On PostgreSQL, where
such transactions run at once (SQLite has one writer at a time).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs import db, service
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.models import Job, JobKind, JobState, Payload, Target, TargetState
from jobs.run import leases, targets
from jobs.run.work import Report
from jobs.settings import Settings
from tests.jobs.helpers import one_delete_started, while_another_writes


@pytest.fixture
def settings(tmp_path: Path, settings: Settings, postgres_url: str) -> Settings:
    data = tmp_path / "pg-data"
    data.mkdir()
    return settings.model_copy(update={"data_dir": data, "database_url": postgres_url})


def _ended(settings: Settings, job_id: str) -> tuple[TargetState, int | None, bool]:
    with db.session_scope(settings.resolved_database_url) as session:
        target = session.scalars(select(Target).where(Target.job_id == job_id)).one()
        job = session.get(Job, job_id)
        assert job is not None
        return target.state, target.error_code, job.finished_at is not None


def test_a_failed_attempt_recorded_while_a_cancel_commits_is_not_retried(
        settings: Settings) -> None:
    job_id, started = one_delete_started(settings)

    def cancel(session: Session) -> None:
        assert service.cancel(session=session, job_id=job_id) == 0  # it runs

    recorded = while_another_writes(  # the result's transaction meets the cancel's
        settings.resolved_database_url, cancel, lambda: targets.finish(
            settings=settings, work=started.work, holder=started.holder,
            error=ContractError(ErrorCode.MACHINE_OFFLINE, "no answer")))
    finished = recorded["result"]
    assert finished.retry_in_s is None
    assert finished.job_done  # the runner says the job ended
    assert _ended(settings, job_id) == (TargetState.CANCELLED, int(ErrorCode.CANCELLED), True)


def test_a_success_recorded_while_a_cancel_commits_leaves_the_job_cancelled(
        settings: Settings) -> None:
    # The cancel finds the one target running and cancels nothing; the job ends cancelled,
    # as a cancel says, whichever of the two commits first.
    job_id, started = one_delete_started(settings)

    def cancel(session: Session) -> None:
        assert service.cancel(session=session, job_id=job_id) == 0

    recorded = while_another_writes(settings.resolved_database_url, cancel, lambda: targets.finish(
        settings=settings, work=started.work, holder=started.holder, error=None))
    assert recorded["result"].job_done
    assert _ended(settings, job_id) == (TargetState.SUCCEEDED, 0, True)
    assert _job_state(settings, job_id) is JobState.CANCELLED


def _job_state(settings: Settings, job_id: str) -> JobState:
    with db.session_scope(settings.resolved_database_url) as session:
        job = session.get(Job, job_id)
        assert job is not None
        return job.state


def test_a_cancel_that_comes_while_a_failed_attempt_is_recorded_cancels_its_retry(
        settings: Settings) -> None:
    job_id, started = one_delete_started(settings)
    finished: dict[str, Any] = {}
    with db.session_scope(settings.resolved_database_url) as recording:
        # The result's transaction has read the job's state, and not committed yet.
        assert targets._cancelled_jobs(recording, [job_id]) == set()
        cancel = threading.Thread(target=lambda: finished.update(cancelled=_cancel(settings,
                                                                                   job_id)))
        cancel.start()
        cancel.join(0.5)
        reports = [Report(settings, started.work, started.holder,
                          ContractError(ErrorCode.MACHINE_OFFLINE, "no answer"),
                          TargetState.SUCCEEDED, None, None)]
        finished["finished"] = targets._serve(recording, reports)[0]
    cancel.join(10)
    assert not cancel.is_alive()
    assert finished["finished"].retry_in_s is not None  # recorded first: put back to retry
    assert finished["cancelled"] == 1  # the cancel, then, cancels that retry
    assert _ended(settings, job_id) == (TargetState.CANCELLED, int(ErrorCode.CANCELLED), True)


def _cancel(settings: Settings, job_id: str) -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        return service.cancel(session=session, job_id=job_id)


def test_a_target_of_a_cancelled_job_put_back_to_run_is_cancelled_and_the_end_said(
        settings: Settings) -> None:
    # The reaper puts back the target of a worker lost mid-attempt, pending; by then its
    # job was cancelled. The runner the reaper queues ends the job instead of running it.
    job_id, started = one_delete_started(settings)
    assert _cancel(settings, job_id) == 0  # running: left to finish, which never comes
    with db.session_scope(settings.resolved_database_url) as session:
        target = session.scalars(select(Target).where(Target.job_id == job_id)).one()
        target.state, target.lease_until = TargetState.PENDING, None  # as the reaper does
    with db.session_scope(settings.resolved_database_url) as session:
        leases.drop_many(session, [started.holder])

    again = targets.begin(settings=settings, job_id=job_id, machine_id="m1")
    assert (again.work, again.job_done) == (None, True)
    assert _ended(settings, job_id) == (TargetState.CANCELLED, int(ErrorCode.CANCELLED), True)
    assert not targets.begin(settings=settings, job_id=job_id, machine_id="m1").job_done


def test_a_retry_and_a_cancel_at_once_take_turns(settings: Settings) -> None:
    job_id, started = one_delete_started(settings)
    targets.finish(settings=settings, work=started.work, holder=started.holder,
                   error=ContractError(ErrorCode.PATH_NOT_FOUND, "O1.NC"))

    def retry(session: Session) -> None:
        assert service.retry_failed(session=session, job_id=job_id) == 1

    cancelled = while_another_writes(  # the cancel meets the retry
        settings.resolved_database_url, retry, lambda: _cancel(settings, job_id))
    assert cancelled["result"] == 1  # the retried target, cancelled before it ran
    assert _ended(settings, job_id) == (TargetState.CANCELLED, int(ErrorCode.CANCELLED), True)


def _rollout(settings: Settings, machines: list[str], *, abort_after_failures: int) -> str:
    """A delete job of one target per machine that stops after so many failures."""
    from jobs.job_options import JobOptions

    with db.session_scope(settings.resolved_database_url) as session:
        for m in machines:
            registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
                {"id": m, "name": m.upper(), "model": "Mock"}), data_dir=settings.data_dir)
        return service.create(session=session, kind=JobKind.DELETE,
                              options=JobOptions(abort_after_failures=abort_after_failures),
                              targets=[service.TargetIn(machineID=m, fileName="O1.NC")
                                       for m in machines]).id


def _failed(settings: Settings, started: Any) -> Report:
    """A started target's report that it failed for good (158)."""
    return Report(settings, started.work, started.holder,
                  ContractError(ErrorCode.PATH_NOT_FOUND, "O1.NC"),
                  TargetState.SUCCEEDED, None, None)


def test_failures_recorded_at_once_abort_a_rollout_at_its_limit(settings: Settings) -> None:
    # `abort_after_failures: 2`: two machines fail at the same moment, each recorded in
    # a transaction of its own worker; the second counts the first's failure.
    job_id = _rollout(settings, ["m1", "m2", "m3", "m4"], abort_after_failures=2)
    started = {m: targets.begin(settings=settings, job_id=job_id, machine_id=m)
               for m in ("m1", "m2")}

    def failed(m: str) -> Report:
        return _failed(settings, started[m])

    def record_alone() -> None:
        with db.session_scope(settings.resolved_database_url) as session:
            targets._serve(session, [failed("m2")])

    other = while_another_writes(  # the other worker's transaction meets this one
        settings.resolved_database_url,
        lambda session: targets._serve(session, [failed("m1")]), record_alone)
    assert other == {"result": None}
    with db.session_scope(settings.resolved_database_url) as session:
        states = {t.machine_id: t.state for t in session.scalars(
            select(Target).where(Target.job_id == job_id))}
    assert states == {"m1": TargetState.FAILED, "m2": TargetState.FAILED,
                      "m3": TargetState.CANCELLED, "m4": TargetState.CANCELLED}


def test_a_rollout_aborted_past_its_limit_names_the_failures_and_the_limit(
        settings: Settings) -> None:
    # `abort_after_failures: 1`: two machines running at once both fail, recorded together.
    job_id = _rollout(settings, ["m1", "m2", "m3"], abort_after_failures=1)
    started = [targets.begin(settings=settings, job_id=job_id, machine_id=m)
               for m in ("m1", "m2")]

    with db.session_scope(settings.resolved_database_url) as session:
        targets._serve(session, [_failed(settings, s) for s in started])

    with db.session_scope(settings.resolved_database_url) as session:
        cancelled = session.scalars(select(Target).where(Target.job_id == job_id,
                                                         Target.machine_id == "m3")).one()
    assert cancelled.state is TargetState.CANCELLED
    assert cancelled.status_msg == "rollout aborted: 2 targets failed (limit 1)"


def test_a_failure_recorded_while_its_rollout_is_being_queued_does_not_wait_for_it(
        settings: Settings) -> None:
    # `abort_after_failures: 1`: the first machine fails while the job's row is still held
    # by the queueing of its tasks (jobs.service.dispatch; seconds for a large rollout),
    # another one running. The failure's transaction, which carries the other results of
    # its worker, goes on. (One that ends the job waits to settle it: that is the row's.)
    job_id = _rollout(settings, ["m1", "m2", "m3"], abort_after_failures=1)
    failed = _failed(settings, targets.begin(settings=settings, job_id=job_id, machine_id="m1"))
    assert targets.begin(settings=settings, job_id=job_id, machine_id="m2").work is not None

    def record() -> None:
        with db.session_scope(settings.resolved_database_url) as session:
            targets._serve(session, [failed])

    recorder = threading.Thread(target=record)
    with db.session_scope(settings.resolved_database_url) as queueing:
        queueing.execute(select(Job.id).where(Job.id == job_id)  # as dispatch holds it
                         .with_for_update(key_share=True))
        recorder.start()
        recorder.join(10)
        recorded_while_held = not recorder.is_alive()
    recorder.join(30)
    assert recorded_while_held
    with db.session_scope(settings.resolved_database_url) as session:
        states = {t.machine_id: t.state for t in session.scalars(
            select(Target).where(Target.job_id == job_id))}
    assert states == {"m1": TargetState.FAILED, "m2": TargetState.RUNNING,
                      "m3": TargetState.CANCELLED}


def test_a_prune_leaves_a_job_being_retried_and_a_program_being_sent(
        settings: Settings) -> None:
    from datetime import timedelta

    job_id, started = one_delete_started(settings)
    targets.finish(settings=settings, work=started.work, holder=started.holder,
                   error=ContractError(ErrorCode.PATH_NOT_FOUND, "O1.NC"))
    with db.session_scope(settings.resolved_database_url) as session:
        program = service.store_payload(session=session, data=b"G0 X9\nM30\n")  # no job uses it

    pruned: dict[str, Any] = {}

    def prune() -> None:
        with db.session_scope(settings.resolved_database_url) as session:
            pruned["n"] = service.prune(session=session, older_than=timedelta(0))

    pruning = threading.Thread(target=prune)
    with db.session_scope(settings.resolved_database_url) as busy:
        assert service.retry_failed(session=busy, job_id=job_id) == 1
        assert service.store_payload(session=busy, data=b"G0 X9\nM30\n") == program
        pruning.start()
        pruning.join(10)  # it skips what this transaction holds, and does not wait for it
        assert not pruning.is_alive()
    assert isinstance(pruned["n"], int)  # the other tests' old jobs, if any
    with db.session_scope(settings.resolved_database_url) as session:
        job = session.get(Job, job_id)
        assert job is not None and job.finished_at is None  # retried, not pruned
        assert session.get(Payload, program) is not None
