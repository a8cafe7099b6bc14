"""The reaper settles what concurrent runners can leave unsettled."""

from __future__ import annotations

from sqlalchemy import update

from jobs import db, service
from jobs.models import Job, JobKind, JobState, Target, TargetState
from jobs.run import reaper


def test_a_job_whose_last_targets_finished_together_is_settled_by_the_reaper(
        settings, add_machines):
    add_machines({"id": "m1", "name": "M", "model": "Mock"})
    with db.session_scope(settings.resolved_database_url) as session:
        job = service.create(session=session, kind=JobKind.DELETE,
                             targets=[service.TargetIn(machineID="m1", fileName="a.nc"),
                                      service.TargetIn(machineID="m1", fileName="b.nc")])
        job_id = job.id
        # Two runners each recorded their target, each seeing the other's still running.
        session.execute(update(Job).where(Job.id == job_id).values(state=JobState.RUNNING))
        session.execute(update(Target).where(Target.job_id == job_id)
                        .values(state=TargetState.SUCCEEDED, error_code=0))
    reaper.reap(settings=settings)
    with db.session_scope(settings.resolved_database_url) as session:
        settled = session.get(Job, job_id)
        assert settled is not None
        assert settled.state is JobState.SUCCEEDED and settled.finished_at is not None
