"""The reaper settles what concurrent runners can leave unsettled."""

from __future__ import annotations

import pytest
from sqlalchemy import select, update

from jobs import db, service
from jobs.backup_models import Backup
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
    assert _reaped(settings, job_id) == (JobState.SUCCEEDED, True)


def test_a_cancelled_job_whose_running_targets_finished_together_is_settled_by_the_reaper(
        settings, add_machines):
    add_machines({"id": "m1", "name": "M", "model": "Mock"},
                 {"id": "m2", "name": "N", "model": "Mock"})
    with db.session_scope(settings.resolved_database_url) as session:
        job = service.create(session=session, kind=JobKind.DELETE,
                             targets=[service.TargetIn(machineID="m1", fileName="a.nc"),
                                      service.TargetIn(machineID="m2", fileName="b.nc")])
        job_id = job.id
        session.execute(update(Target).where(Target.job_id == job_id)
                        .values(state=TargetState.RUNNING))
    with db.session_scope(settings.resolved_database_url) as session:
        assert service.cancel(session=session, job_id=job_id) == 0  # both left to finish
    with db.session_scope(settings.resolved_database_url) as session:
        # Their runners each recorded one, each seeing the other's still running.
        session.execute(update(Target).where(Target.job_id == job_id)
                        .values(state=TargetState.SUCCEEDED, error_code=0))
    assert _reaped(settings, job_id) == (JobState.CANCELLED, True)


def _reaped(settings, job_id: str) -> tuple[JobState, bool]:
    """The job's state after the reaper's round, and whether it is finished."""
    reaper.reap(settings=settings)
    with db.session_scope(settings.resolved_database_url) as session:
        settled = session.get(Job, job_id)
        assert settled is not None
        return settled.state, settled.finished_at is not None


def _running_run(settings, *, heard_ago_s: float) -> str:
    """A dnc_run job whose target's lease ran out, its run last heard of `heard_ago_s` ago."""
    from datetime import timedelta

    from jobs.models import Run, RunState, utcnow

    now = utcnow()
    with db.session_scope(settings.resolved_database_url) as session:
        job = service.create(session=session, kind=JobKind.DNC_RUN,
                             targets=[service.TargetIn(machineID="m1", fileName="P.NC")])
        session.execute(update(Target).where(Target.job_id == job.id).values(
            state=TargetState.RUNNING, lease_until=now - timedelta(seconds=1), attempts=1))
        session.add(Run(job_id=job.id, position=0, machine_id="m1", program_name="P.NC",
                        program_id="0" * 64, state=RunState.RUNNING, started_by="test",
                        created_at=now, started_at=now, start_line=1, header=[],
                        lines_total=10, lines_sent=5, last_line=3, stop_requested=False,
                        updated_at=now - timedelta(seconds=heard_ago_s)))
        return job.id


def _target_state(settings, job_id: str) -> TargetState:
    with db.session_scope(settings.resolved_database_url) as session:
        return session.query(Target).filter_by(job_id=job_id).one().state


def test_a_run_still_heard_of_keeps_its_target_though_its_lease_ran_out(
        settings, add_machines):
    """A worker too busy to renew its leases is still feeding the machine: queueing the
    target again would start a second feed of the same program."""
    add_machines({"id": "m1", "name": "M", "model": "Mock"})
    job_id = _running_run(settings, heard_ago_s=1)

    reaper.reap(settings=settings)

    assert _target_state(settings, job_id) is TargetState.RUNNING


def test_a_run_not_heard_of_for_a_lease_period_is_recovered_like_any_target(
        settings, add_machines):
    add_machines({"id": "m1", "name": "M", "model": "Mock"})
    job_id = _running_run(settings, heard_ago_s=settings.lease_ttl_s + 5)

    reaper.reap(settings=settings)

    assert _target_state(settings, job_id) is TargetState.PENDING


def test_a_job_still_being_queued_is_left_to_its_api_however_long_that_takes(
        request, settings, monkeypatch):
    # Queueing a job of 100,000 targets takes the API longer than the reaper waits before
    # it calls a `queued` job lost: it must not queue the job a second time meanwhile.
    # PostgreSQL only: the API holds the job's row; SQLite, the embedded mode's database,
    # has no row locks (and there a dispatch of its fleets takes milliseconds).
    from datetime import timedelta

    from jobs.fleet import registry
    from jobs.models import utcnow
    from jobs.run import queue

    url = request.getfixturevalue("postgres_url")
    s = settings.model_copy(update={"database_url": url})
    with db.session_scope(url) as session:
        for m in ("m1", "m2"):
            registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
                {"id": m, "name": m.upper(), "model": "Mock"}), data_dir=settings.data_dir)
        job = service.create(session=session, kind=JobKind.DELETE,
                             targets=[service.TargetIn(machineID=m, fileName="a.nc")
                                      for m in ("m1", "m2")])
        job_id = job.id
        session.execute(update(Job).where(Job.id == job_id).values(
            created_at=utcnow() - timedelta(seconds=reaper.UNQUEUED_AFTER_S * 3)))
    sent: list[tuple[str, str]] = []
    reaped: list[int] = []

    def enqueue(settings_, runs):
        for run in runs:
            sent.append(run)
            if len(sent) == 1:  # the API is half-way through queueing the job
                reaped.append(reaper.reap(settings=s))

    monkeypatch.setattr(queue, "enqueue_machines", enqueue)
    assert service.dispatch(settings=s, job_id=job_id) == 2

    assert reaped == [0]
    assert sorted(sent) == [(job_id, "m1"), (job_id, "m2")]  # each machine's task once
    with db.session_scope(url) as session:
        assert session.get(Job, job_id).state is JobState.RUNNING


def _lost_or_waiting(settings, add_machines, monkeypatch):
    """A job on m1 and m2 queued three `redispatch_after_s` ago, m1's task delivered since
    (its target running), m2's target still pending; returns the job id and the list that
    every task the reaper queues is added to."""
    from datetime import timedelta

    from jobs.models import utcnow
    from jobs.run import queue, targets

    add_machines(*({"id": m, "name": m.upper(), "model": "Mock"} for m in ("m1", "m2", "m3")))
    queued_at = utcnow() - timedelta(seconds=3 * settings.redispatch_after_s)
    with db.session_scope(settings.resolved_database_url) as session:
        job = service.create(session=session, kind=JobKind.DELETE,
                             targets=[service.TargetIn(machineID=m, fileName="a.nc")
                                      for m in ("m1", "m2")])
        session.execute(update(Job).where(Job.id == job.id).values(state=JobState.RUNNING))
        session.execute(update(Target).where(Target.job_id == job.id)
                        .values(dispatched_at=queued_at))
        job_id = job.id
    assert targets.begin(settings=settings, job_id=job_id, machine_id="m1").work is not None
    sent: list[tuple[str, str]] = []
    monkeypatch.setattr(queue, "enqueue_machines",
                        lambda settings_, runs: sent.extend(runs))
    return job_id, sent


def test_a_target_waiting_behind_a_backlog_is_not_queued_again(
        settings, add_machines, monkeypatch):
    # A rollout to 100,000 machines takes minutes to drain from the queue: while the queue
    # delivers tasks queued as long ago as a target's own, that target is waiting in it,
    # and queueing it again every `redispatch_after_s` only adds tasks that find it done.
    s = settings.model_copy(update={"redispatch_after_s": 60.0})
    job_id, sent = _lost_or_waiting(s, add_machines, monkeypatch)

    assert reaper.reap(settings=s) == 0
    assert sent == []


def test_a_target_the_queue_went_past_is_queued_again(settings, add_machines, monkeypatch):
    # A task queued a whole `redispatch_after_s` after the target's own was delivered: the
    # queue is first in, first out, so the target's message was lost (a Redis restart).
    from jobs.run import targets

    s = settings.model_copy(update={"redispatch_after_s": 60.0})
    job_id, sent = _lost_or_waiting(s, add_machines, monkeypatch)
    with db.session_scope(s.resolved_database_url) as session:
        later = service.create(session=session, kind=JobKind.DELETE,
                               targets=[service.TargetIn(machineID="m3", fileName="a.nc")])
        later_id = later.id
    assert targets.begin(settings=s, job_id=later_id, machine_id="m3").work is not None

    assert reaper.reap(settings=s) == 1
    assert sent == [(job_id, "m2")]


def test_a_target_queued_long_ago_is_queued_again_when_nothing_was_delivered_lately(
        settings, add_machines, monkeypatch):
    from jobs.run import deliveries

    s = settings.model_copy(update={"redispatch_after_s": 60.0})
    job_id, sent = _lost_or_waiting(s, add_machines, monkeypatch)
    deliveries.forget()  # a worker that took nothing from the queue in a while

    assert reaper.reap(settings=s) == 1
    assert sent == [(job_id, "m2")]


def test_the_work_files_of_a_backup_whose_assembler_died_after_registering_it_are_removed(
        settings, add_machines, monkeypatch):
    # Killed between registering the ZIP and removing the fetched files (as large as the
    # backup): no delivery assembles the job again, as it has its backup.
    from types import SimpleNamespace

    from jobs import folders
    from jobs.backup import store
    from tests.jobs.backup.test_assembly import fetched_job
    from tests.jobs.helpers import mock_file

    class Killed(BaseException):
        """The assembler's process ending there."""

    def killed(*args, **kwargs):
        raise Killed

    add_machines({"id": "m1", "name": "M1", "model": "Mock"})
    mock_file(settings, "m1", "P1.nc", "G0 X1\n")
    job_id = fetched_job(settings, "m1")
    monkeypatch.setattr(store, "shutil", SimpleNamespace(rmtree=killed))
    with pytest.raises(Killed):
        store.assemble(settings=settings, job_id=job_id)
    monkeypatch.undo()
    assert folders.job_folder(settings, job_id).is_dir()

    reaper.reap(settings=settings)

    assert not folders.job_folder(settings, job_id).exists()
    with db.session_scope(settings.resolved_database_url) as session:
        assert [b.job_id for b in session.scalars(select(Backup))] == [job_id]


def _finished_backup(settings, add_machines, monkeypatch) -> tuple[str, list[str]]:
    """A backup job on m1, fetched and finished seconds ago without its ZIP; returns its id
    and the list that every assembly the reaper asks for is added to."""
    from datetime import timedelta

    from jobs.models import utcnow
    from jobs.run import queue
    from tests.jobs.backup.test_assembly import fetched_job
    from tests.jobs.helpers import mock_file

    add_machines({"id": "m1", "name": "M1", "model": "Mock"})
    mock_file(settings, "m1", "P1.nc", "G0 X1\n")
    job_id = fetched_job(settings, "m1")
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(Job).where(Job.id == job_id)
                        .values(finished_at=utcnow() - timedelta(seconds=5)))
    asked: list[str] = []
    monkeypatch.setattr(queue, "enqueue_assembly", lambda settings_, job: asked.append(job))
    return job_id, asked


def test_a_backup_whose_assembly_is_writing_its_zip_is_not_assembled_a_second_time(
        settings, add_machines, monkeypatch):
    # A large backup's ZIP takes minutes to write: a second assembly beside it would write
    # a second copy, twice the room and the disk's time, only to throw it away.
    import threading

    from jobs.backup import store

    job_id, asked = _finished_backup(settings, add_machines, monkeypatch)
    writing, held = threading.Event(), threading.Event()
    pieces = store.joined

    def held_after_a_piece(members, size):
        for piece in pieces(members, size):
            yield piece
            writing.set()
            held.wait(30)

    monkeypatch.setattr(store, "joined", held_after_a_piece)
    assembly = threading.Thread(target=store.assemble,
                                kwargs={"settings": settings, "job_id": job_id})
    assembly.start()
    try:
        assert writing.wait(30)
        reaper.reap(settings=settings)
    finally:
        held.set()
        assembly.join(30)

    assert asked == []
    with db.session_scope(settings.resolved_database_url) as session:
        assert [b.job_id for b in session.scalars(select(Backup))] == [job_id]


@pytest.mark.parametrize("writer", ["dead", "quiet elsewhere"])
def test_a_backup_whose_assembler_died_or_went_quiet_while_writing_is_assembled_again(
        settings, add_machines, monkeypatch, writer):
    import os
    import subprocess
    import time

    from jobs import folders
    from jobs.backup import store
    from worker.transports import parts

    job_id, asked = _finished_backup(settings, add_machines, monkeypatch)
    ended = subprocess.Popen(["true"])
    ended.wait()
    host = parts.WRITER if writer == "dead" else "otherhost"
    part = (folders.backup_dir(settings)
            / f"{store.ASSEMBLING}{host}-{ended.pid}-B-{job_id}-b1.zip.part")
    part.write_bytes(b"PK\x03\x04 half a ZIP")
    if writer == "quiet elsewhere":
        untouched_since = time.time() - parts.STILL_WRITING_S - 60
        os.utime(part, (untouched_since, untouched_since))

    reaper.reap(settings=settings)

    assert asked == [job_id]
