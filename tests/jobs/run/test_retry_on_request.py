"""A retry on request (`dncq retry`, POST /api/jobs/{id}/retry) gives the failed targets
the tries a new job would have: its max_attempts and its deliver_within window count from
the retry, not from the job's first attempt. A short outage during the retry is retried
through, as it would be the first time."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import update

from jobs import db, service
from jobs.errors import ContractError, ErrorCode
from jobs.job_options import JobOptions
from jobs.models import Job, JobKind, Target, utcnow
from jobs.run import targets
from jobs.settings import Settings


def _job(settings: Settings, add_machines, options: JobOptions) -> str:
    add_machines({"id": "m1", "name": "M", "model": "Mock"})
    with db.session_scope(settings.resolved_database_url) as session:
        return service.create(session=session, kind=JobKind.DELETE, options=options,
                              targets=[service.TargetIn(machineID="m1", fileName="O1.NC")]).id


def _offline_attempt(settings: Settings, job_id: str) -> float | None:
    """One attempt that finds the machine offline (its retry delay waived before it); the
    delay to the next try, None when the target failed for good."""
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(Target).where(Target.job_id == job_id)
                        .values(next_attempt_at=None))
    started = targets.begin(settings=settings, job_id=job_id, machine_id="m1")
    assert started.work is not None and started.holder is not None
    return targets.finish(settings=settings, work=started.work, holder=started.holder,
                          error=ContractError(ErrorCode.MACHINE_OFFLINE, "no answer")).retry_in_s


def _retried(settings: Settings, job_id: str) -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        assert service.retry_failed(session=session, job_id=job_id) == 1


def test_a_retry_on_request_gets_the_jobs_max_attempts_again(settings, add_machines) -> None:
    job_id = _job(settings, add_machines, JobOptions(max_attempts=2))
    first = [_offline_attempt(settings, job_id) for _ in range(2)]
    _retried(settings, job_id)

    again = [_offline_attempt(settings, job_id) for _ in range(2)]

    assert first[0] is not None and first[1] is None  # two tries, then failed
    assert again[0] is not None and again[1] is None  # two tries again, not one


def test_a_retry_on_request_opens_the_deliver_within_window_again(settings,
                                                                  add_machines) -> None:
    job_id = _job(settings, add_machines, JobOptions(deliver_within=600))
    with db.session_scope(settings.resolved_database_url) as session:  # made long ago
        session.execute(update(Job).where(Job.id == job_id)
                        .values(created_at=utcnow() - timedelta(hours=2)))
    closed = _offline_attempt(settings, job_id)
    _retried(settings, job_id)

    reopened = _offline_attempt(settings, job_id)

    assert closed is None  # the window had closed: failed at once
    assert reopened is not None  # ten minutes from the retry
