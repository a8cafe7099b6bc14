"""Faults of the distributed mode: Redis restarted under a working worker, a worker whose
Celery fails, a worker killed, a job committed but never queued, the database lost while
an attempt or a task starts."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta

import pytest
import redis

from jobs import db
from jobs.fleet import registry
from jobs.models import Job, JobState, TargetState, utcnow
from jobs.run import queue
from jobs.run import targets as runs
from tests.jobs.helpers import wait_until
from tests.jobs.run.test_crash import (
    PROGRAM,
    assert_files_exactly_once,
    at_least,
    claim,
    create,
    files_of,
    finished,
    fleet,
    machine_file,
    register,
    submit,
    target_rows,
    targets,
)
from tests.servers import PostgresServer, postgres_of_its_own
from tests.workers import WorkerProcess
from worker import operations, runner

pytestmark = pytest.mark.slow

RESTARTS = 4


def said(worker: WorkerProcess, text: str) -> int:
    return worker.log().count(text)


def wait_to_say_again(worker: WorkerProcess, text: str, *, timeout_s: float = 30) -> None:
    """Block until the worker logs `text` once more than now, or ends."""
    before = said(worker, text)
    wait_until(lambda: said(worker, text) > before or worker.proc.poll() is not None,
               timeout_s=timeout_s)


@pytest.mark.parametrize("pool", ["threads", "gevent"])
def test_a_worker_keeps_working_through_repeated_redis_restarts(
        crash_settings, restarted_redis, add_machines, start_worker, pool):
    s = crash_settings
    machines_n = 64  # many more machines than slots: tasks wait in Redis at every restart
    add_machines(*fleet(machines_n, latency_ms=300))
    worker = start_worker("w", s, concurrency=2, pool=pool)
    worker.wait_ready()
    job_id = submit(s, targets(machines_n, 2))

    for _ in range(RESTARTS):
        # Each time with tasks delivered on the new connection and not yet acknowledged.
        wait_to_say_again(worker, "] received")
        assert not finished(s, job_id), "the job ended before the last restart"
        lost = said(worker, "Connection to broker lost") + said(worker, "Cannot connect to")
        restarted_redis.kill()
        # The worker noticed: its connection dropped, or (between two of its steps) it could
        # not connect again.
        wait_until(lambda: said(worker, "Connection to broker lost")  # noqa: B023
                   + said(worker, "Cannot connect to") > lost  # noqa: B023
                   or worker.proc.poll() is not None, timeout_s=30)
        connected = said(worker, "Connected to")
        restarted_redis.start()
        # Celery's reconnect backs off (2 s, 4 s, ...): the next kill waits for it.
        wait_until(lambda: said(worker, "Connected to") > connected  # noqa: B023
                   or worker.proc.poll() is not None, timeout_s=60)
        assert worker.proc.poll() is None, "the worker ended instead of reconnecting"
    wait_until(lambda: finished(s, job_id) or worker.proc.poll() is not None, timeout_s=60)

    assert worker.proc.poll() is None, "the worker ended instead of reconnecting"
    assert "Unrecoverable error" not in worker.log()
    rows = target_rows(s, job_id)
    assert {t.state for t in rows} == {TargetState.SUCCEEDED}
    for t in rows:
        assert [a.error_code for a in t.history].count(0) == 1, t.history  # one result each
    assert_files_exactly_once(s, machines_n, 2)


def test_a_worker_whose_celery_fails_exits_non_zero(crash_settings, start_worker, tmp_path):
    # Celery's start fails (its pid file cannot be written): the service must see a failure.
    worker = start_worker("p", crash_settings, args=["--pidfile", str(tmp_path / "no" / "w.pid")])

    assert worker.proc.wait(60) == 1
    assert "Unrecoverable error" in worker.log()


@pytest.fixture
def restartable_postgres() -> Iterator[PostgresServer]:
    """A PostgreSQL server of the test's own, which the test may stop and start."""
    with postgres_of_its_own() as server:
        yield server


def test_a_database_lost_while_loading_the_payload_is_retried_not_failed(
        settings, restartable_postgres, monkeypatch):
    # The payload must come from the database: not from an earlier test's cached copy.
    monkeypatch.setattr(operations, "PAYLOADS", operations.PayloadCache())
    s = settings.model_copy(update={"database_url": restartable_postgres.url,
                                    "retry_base_s": 0.0, "retry_max_s": 0.0})
    db.upgrade(s.resolved_database_url)
    register(s, fleet(1))
    job_id = create(s, [{"machineID": "m000", "fileName": "P.nc"}])
    work, holder = claim(s, job_id)
    with db.session_scope(s.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id="m000")

    restartable_postgres.stop()  # after the claim, before the payload is read
    outcome = runner.attempt(s, spec, work, None)
    restartable_postgres.start()
    runs.finish(settings=s, work=work, holder=holder, error=outcome.error)

    [t] = target_rows(s, job_id)
    assert (t.state, t.error_code) == (TargetState.PENDING, 20017)  # to be tried again
    assert "database unavailable" in t.status_msg
    again, _ = claim(s, job_id)
    with files_of(s, "m000") as files:
        assert operations.execute(s, files, again).error is None
    assert again.attempt == 2
    assert machine_file(s, "m000", "P.nc").read_bytes() == PROGRAM


def test_a_machine_task_that_finds_the_database_gone_ends_without_raising(
        settings, restartable_postgres, caplog):
    # A task that raises makes Celery keep a copy of its whole traceback: an outage's
    # failed tasks once held 30 MB of those, and the worker's memory stayed grown after.
    s = settings.model_copy(update={"database_url": restartable_postgres.url,
                                    "redispatch_after_s": 0.0})  # no wait for it to return
    db.upgrade(s.resolved_database_url)
    register(s, fleet(1))
    job_id = create(s, [{"machineID": "m000", "fileName": "P.nc"}])

    restartable_postgres.stop()
    runner.run_machine(s, job_id, "m000")
    restartable_postgres.start()

    assert "stopped: database unavailable (OperationalError)" in caplog.text
    [t] = target_rows(s, job_id)
    assert t.state is TargetState.PENDING  # the reaper queues it again


def test_a_machine_task_that_loses_the_database_mid_target_leaves_it_to_its_lease(
        settings, restartable_postgres, caplog):
    s = settings.model_copy(update={"database_url": restartable_postgres.url})
    db.upgrade(s.resolved_database_url)
    register(s, fleet(1, latency_ms=3000))  # each machine operation: time to stop the server
    # Two targets: the first one's finish is waited for (it claims the next), and fails.
    job_id = create(s, [{"machineID": "m000", "fileName": f"P{i}.nc"} for i in range(2)])

    with ThreadPoolExecutor(1) as pool:
        task = pool.submit(runner.run_machine, s, job_id, "m000")
        wait_until(lambda: TargetState.RUNNING in {t.state for t in target_rows(s, job_id)})
        restartable_postgres.stop()
        assert task.result(timeout=120) is None  # it raised before
    restartable_postgres.start()

    assert "stopped: database unavailable" in caplog.text
    first, second = target_rows(s, job_id)
    assert (first.state, second.state) == (TargetState.RUNNING, TargetState.PENDING)
    assert first.lease_until is not None  # recovered by the reaper once it runs out


OLD_REDISPATCH_S = 60.0  # the default of redispatch_after_s: the only way back before


def test_a_killed_gevent_worker_held_no_more_than_its_pool_and_its_tasks_run_elsewhere(
        crash_settings, redis_server, add_machines, start_worker):
    # A gevent worker runs twice its slots in greenlets (the others claim ahead) and its
    # prefetch window is twice that. It used to take one message more than its pool could
    # start, and kept it in its memory only: killed, it took that one with it, and only the
    # reaper gave it back. It now holds what its pool runs, each claimed in the database.
    s = crash_settings.model_copy(update={"redispatch_after_s": OLD_REDISPATCH_S})
    machines_n, pool = 16, 4  # two slots, two greenlets claiming ahead
    add_machines(*fleet(machines_n, latency_ms=300))
    first = start_worker("a", s, concurrency=2, pool="gevent")
    first.wait_ready()
    job_id = submit(s, targets(machines_n, 3))
    wait_until(lambda: at_least(s, job_id, succeeded=2, running=2), timeout_s=30)

    first.kill()
    killed_at = utcnow()
    # One task per machine: those no longer in Redis were delivered to the dead worker; a
    # machine whose targets all ended was acknowledged.
    delivered = machines_n - redis.Redis.from_url(redis_server.url).llen(queue.QUEUE)
    rows = target_rows(s, job_id)
    ended = {t.machine_id for t in rows} - {t.machine_id for t in rows if not t.state.final}
    assert delivered - len(ended) <= pool
    start_worker("b", s, concurrency=8, pool="gevent")
    wait_until(lambda: finished(s, job_id), timeout_s=OLD_REDISPATCH_S)

    rows = target_rows(s, job_id)
    assert {t.state for t in rows} == {TargetState.SUCCEEDED}
    last_start = max(t.started_at for t in rows if t.started_at is not None)
    assert last_start < killed_at + timedelta(seconds=OLD_REDISPATCH_S)
    assert_files_exactly_once(s, machines_n, 3)


def test_a_job_committed_but_never_queued_is_started_by_the_reaper(
        crash_settings, add_machines, start_worker):
    # What an API process killed between committing a job and sending its tasks leaves.
    s = crash_settings.model_copy(update={"redispatch_after_s": OLD_REDISPATCH_S})
    machines_n = 6
    add_machines(*fleet(machines_n, latency_ms=20))
    start_worker("w", s, pool="threads").wait_ready()
    job_id = create(s, targets(machines_n, 2))  # recorded, no task sent

    wait_until(lambda: finished(s, job_id), timeout_s=OLD_REDISPATCH_S)

    rows = target_rows(s, job_id)
    assert {t.state for t in rows} == {TargetState.SUCCEEDED}
    assert [t.attempts for t in rows] == [1] * len(rows)
    with db.session_scope(s.resolved_database_url) as session:
        job = session.get(Job, job_id)
        assert job is not None
        created_at = job.created_at
    first_start = min(t.started_at for t in rows if t.started_at is not None)
    assert first_start < created_at + timedelta(seconds=OLD_REDISPATCH_S)
    assert_files_exactly_once(s, machines_n, 2)


def test_a_task_received_while_the_database_is_down_runs_once_it_is_back(
        crash_settings, restartable_postgres, start_worker):
    s = crash_settings.model_copy(update={"database_url": restartable_postgres.url,
                                          "redispatch_after_s": OLD_REDISPATCH_S})
    db.upgrade(s.resolved_database_url)
    register(s, fleet(1, latency_ms=20))
    worker = start_worker("w", s, pool="threads")
    worker.wait_ready()
    job_id = create(s, [{"machineID": "m000", "fileName": "P.nc"}])
    with db.session_scope(s.resolved_database_url) as session:  # queued, as dispatch leaves it
        job = session.get(Job, job_id)
        assert job is not None
        job.state, created_at = JobState.RUNNING, job.created_at

    restartable_postgres.stop()
    received = said(worker, "] received")
    queue.enqueue_machine(s, job_id, "m000")
    wait_until(lambda: said(worker, "] received") > received, timeout_s=30)
    restartable_postgres.start()
    wait_until(lambda: finished(s, job_id), timeout_s=OLD_REDISPATCH_S / 2)

    [t] = target_rows(s, job_id)
    assert (t.state, t.attempts) == (TargetState.SUCCEEDED, 1)
    # by the task that waited, not by the reaper's queueing it again
    assert t.started_at is not None
    assert t.started_at < created_at + timedelta(seconds=OLD_REDISPATCH_S)
    assert machine_file(s, "m000", "P.nc").read_bytes() == PROGRAM
