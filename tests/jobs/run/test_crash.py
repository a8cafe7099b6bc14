"""Recovery from a killed worker, a lost queue, a restarted database and a killed `dncq serve`."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import selectinload

from jobs import db, rollout, service
from jobs.api.app import create_app
from jobs.backup import manifests, store
from jobs.backup_models import Backup, BackupStatus
from jobs.errors import ContractError, ErrorCode
from jobs.job_options import JobOptions
from jobs.models import Job, JobKind, Payload, Target, TargetState
from jobs.run import reaper, settle
from jobs.run import targets as runs
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.helpers import on_machine, wait_until
from tests.live_server import HTTP_TIMEOUT_S, serving
from tests.servers import (
    PostgresServer,
    free_port,
    postgres_of_its_own,
    stop_process,
    wait_for_port,
)
from tests.workers import WorkerProcess, worker_env
from worker import operations
from worker.transports.mock import PART_PREFIX

pytestmark = pytest.mark.slow

PROGRAM = b"G21 G90\nG0 X0 Y0\nG1 X10 F100\nM30\n"
MACHINES = 10
FILES_PER_MACHINE = 4
INTERRUPTED = "interrupted: worker lost"  # what the reaper writes on a lost attempt
# Long enough that a job of FILES_PER_MACHINE rounds is seen mid-job (some targets done,
# others running) by a look every 50 ms on a fast host, and a kill or an outage meets it there.
OPERATION_MS = 600


@pytest.mark.parametrize("pool", ["threads", "gevent"])
def test_a_worker_killed_mid_job_leaves_every_target_done_exactly_once(
        crash_settings, add_machines, start_worker, pool):
    s = crash_settings
    add_machines(*fleet(MACHINES, latency_ms=OPERATION_MS))
    first = start_worker("a", s, pool=pool)
    first.wait_ready()
    job_id = submit(s, targets(MACHINES, FILES_PER_MACHINE))
    wait_until(lambda: at_least(s, job_id, succeeded=MACHINES // 2, running=3), timeout_s=30)

    at_kill = kill_between_writes(first, s, job_id)
    second = start_worker("b", s, pool=pool)
    wait_until(lambda: finished(s, job_id), timeout_s=60)

    rows = target_rows(s, job_id)
    assert {t.state for t in rows} == {TargetState.SUCCEEDED}
    for t in rows:
        assert [a.error_code for a in t.history].count(0) == 1, t.history  # one result each
        if at_kill[t.id] is TargetState.SUCCEEDED:  # never run again
            assert (t.attempts, workers(t)) == (1, [first.worker_name])
        elif at_kill[t.id] is TargetState.RUNNING:  # the lost attempt, then the second worker's
            assert (t.attempts, workers(t)) == (2, [first.worker_name, second.worker_name])
            assert (t.history[0].error_code, t.history[0].error_msg) == (None, INTERRUPTED)
        else:
            assert (t.attempts, workers(t)) == (1, [second.worker_name])
    assert set(at_kill.values()) >= {TargetState.SUCCEEDED, TargetState.RUNNING}
    assert_files_exactly_once(s, MACHINES, FILES_PER_MACHINE)


@pytest.mark.parametrize("pool", ["threads", "gevent"])
def test_a_worker_stopped_in_good_order_records_every_result_before_it_exits(
        crash_settings, add_machines, start_worker, pool):
    # Long leases: a result the worker failed to record would show as a target still running.
    s = crash_settings.model_copy(update={"lease_ttl_s": 60.0})
    # A second per operation: all ten run at once, and the look below must see them running.
    add_machines(*fleet(MACHINES, latency_ms=1000))
    first = start_worker("a", s, pool=pool)
    first.wait_ready()
    job_id = submit(s, targets(MACHINES, 1))  # one target per machine: each its machine's last
    wait_until(lambda: at_least(s, job_id, running=3), timeout_s=30)

    first.stop()  # SIGTERM: the running targets finish, then the worker exits

    assert first.proc.returncode == 0
    by_state = {t.id: t.state for t in target_rows(s, job_id)}
    assert TargetState.RUNNING not in by_state.values()
    assert list(by_state.values()).count(TargetState.SUCCEEDED) >= 3
    second = start_worker("b", s, pool=pool)
    wait_until(lambda: finished(s, job_id), timeout_s=60)
    for t in target_rows(s, job_id):
        assert t.state is TargetState.SUCCEEDED
        assert [(a.error_code, a.worker) for a in t.history] == [  # once, by one worker
            (0, (first if by_state[t.id] is TargetState.SUCCEEDED else second).worker_name)]
    assert_files_exactly_once(s, MACHINES, 1)


@pytest.mark.parametrize("pool", ["threads", "gevent"])
def test_a_job_completes_after_redis_is_killed_and_started_again(
        crash_settings, restarted_redis, add_machines, start_worker, pool):
    s = crash_settings
    # Many more machines than operation slots (4; a gevent worker claims 8 ahead): tasks
    # still wait in Redis when the first target succeeds, with seconds to spare on a slow host.
    machines_n = 24
    add_machines(*fleet(machines_n, latency_ms=100))
    worker = start_worker("w", s, concurrency=4, pool=pool)
    worker.wait_ready()
    job_id = submit(s, targets(machines_n, FILES_PER_MACHINE))
    wait_until(lambda: at_least(s, job_id, succeeded=1), timeout_s=30)
    assert machines_not_started(s, job_id), "every machine started before Redis went away"

    restarted_redis.kill()  # the queued tasks of the machines not started are gone
    worker.wait_for_log("Connection to broker lost", timeout_s=30)
    restarted_redis.start()
    wait_until(lambda: finished(s, job_id), timeout_s=60)

    assert worker.proc.poll() is None, "the worker ended instead of reconnecting"
    rows = target_rows(s, job_id)
    assert {t.state for t in rows} == {TargetState.SUCCEEDED}
    assert [(t.attempts, [a.error_code for a in t.history]) for t in rows] \
        == [(1, [0])] * len(rows)
    assert_files_exactly_once(s, machines_n, FILES_PER_MACHINE)


def test_requests_made_while_redis_is_down_are_answered_recorded_and_run_once_it_is_back(
        crash_settings, restarted_redis, add_machines, start_worker):
    # They answered 500 (kombu's BatchPublishError) for jobs recorded whole, which the
    # reaper then ran: a client that tried again sent, replaced or deleted twice.
    s = crash_settings.model_copy(update={"batch_wait_s": 1.0})
    add_machines(*fleet(2, latency_ms=0))
    restarted_redis.kill()
    with TestClient(create_app(s), headers={"X-Api-Key": API_KEY}) as client:
        made = client.post("/api/jobs", json={
            "kind": "send", "content": PROGRAM.decode(),
            "targets": [{"machineID": "m000", "fileName": "P0.nc"}]})
        batch = client.post("/api/cnc/batchSendFile", json={
            "content": PROGRAM.decode(), "targets": [{"machineID": "m001", "fileName": "P0.nc"}]})
    assert made.status_code == 202 and made.json()["state"] == "queued"
    job_ids = made.json()["id"], batch.headers["X-Dncq-Job"]
    assert batch.status_code == 200
    assert batch.json() == [{"errorCode": ErrorCode.STILL_RUNNING.value,
                             "errorMsg": f"Still running: job {job_ids[1]}."}]

    restarted_redis.start()
    start_worker("w", s, pool="gevent").wait_ready()
    for job_id in job_ids:
        wait_until(lambda job_id=job_id: finished(s, job_id), timeout_s=60)
        assert [(t.state, t.attempts) for t in target_rows(s, job_id)] \
            == [(TargetState.SUCCEEDED, 1)]
    assert_files_exactly_once(s, 2, 1)


@pytest.fixture
def restartable_postgres() -> Iterator[PostgresServer]:
    """A PostgreSQL server of the test's own, which the test may stop and start."""
    with postgres_of_its_own() as server:
        yield server


@pytest.mark.parametrize("pool", ["threads", "gevent"])
def test_a_job_completes_after_postgresql_is_restarted(
        crash_settings, restartable_postgres, start_worker, pool):
    s = crash_settings.model_copy(update={"database_url": restartable_postgres.url})
    db.upgrade(s.resolved_database_url)
    register(s, fleet(MACHINES, latency_ms=OPERATION_MS))
    worker = start_worker("w", s, pool=pool)
    worker.wait_ready()
    job_id = submit(s, targets(MACHINES, FILES_PER_MACHINE))
    wait_until(lambda: at_least(s, job_id, succeeded=MACHINES // 2, running=3), timeout_s=30)

    restartable_postgres.stop()  # results the runners cannot record, slots they cannot free
    time.sleep(2 * s.lease_ttl_s)
    restartable_postgres.start()
    wait_until(lambda: finished(s, job_id), timeout_s=90)

    assert worker.proc.poll() is None, "the worker ended instead of reconnecting"
    rows = target_rows(s, job_id)
    assert {t.state for t in rows} == {TargetState.SUCCEEDED}, \
        [(t.position, t.state, t.error_msg) for t in rows if t.state != TargetState.SUCCEEDED]
    for t in rows:
        assert [a.error_code for a in t.history].count(0) == 1, t.history  # one result each
    assert any(t.attempts > 1 for t in rows), "the outage met no target in flight"
    assert_files_exactly_once(s, MACHINES, FILES_PER_MACHINE)


def test_the_api_answers_its_first_request_after_postgresql_restarted(
        settings, restartable_postgres):
    s = settings.model_copy(update={"database_url": restartable_postgres.url})
    db.upgrade(s.resolved_database_url)
    with TestClient(create_app(s), headers={"X-Api-Key": API_KEY}) as client:
        assert client.get("/api/jobs").status_code == 200  # its connection now in the pool

        restartable_postgres.stop()
        restartable_postgres.start()

        assert client.get("/api/jobs").status_code == 200


def test_the_embedded_mode_killed_mid_job_finishes_the_job_once_started_again(tmp_path):
    fleet_file = tmp_path / "fleet.yaml"
    fleet_file.write_text(yaml.safe_dump({"machines": fleet(MACHINES, latency_ms=OPERATION_MS)}))
    data = tmp_path / "data"
    port = free_port()
    env = {**worker_env(Settings(data_dir=data, lease_ttl_s=2.0, reaper_interval_s=0.3,
                                 redispatch_after_s=1.0)), "DNCQ_PORT": str(port)}
    env.pop("DNCQ_DATABASE_URL")  # the embedded default: SQLite in the data folder
    log = tmp_path / "serve.log"

    with contextlib.ExitStack() as running:

        def serve() -> subprocess.Popen[bytes]:
            with open(log, "ab") as out:
                proc = subprocess.Popen([sys.executable, "-m", "jobs.cli", "serve", "--fleet",
                                         str(fleet_file)], env=env, stdout=out, stderr=out)
            running.callback(stop_process, proc)
            wait_for_port(port, timeout_s=60)
            return proc

        first = serve()
        http = running.enter_context(httpx.Client(
            base_url=f"http://127.0.0.1:{port}", timeout=30,
            headers={"X-Api-Key": (data / "api-key").read_text().strip()}))
        job_id = http.post("/api/jobs", json={
            "kind": "send", "content": PROGRAM.decode(),
            "targets": targets(MACHINES, FILES_PER_MACHINE)}).json()["id"]
        counts = lambda: http.get(f"/api/jobs/{job_id}").json()["counts"]  # noqa: E731
        wait_until(lambda: counts()["succeeded"] >= MACHINES and counts()["running"] >= 3,
                   timeout_s=60)

        first.kill()  # SIGKILL: API, queue consumer and runners all gone at once
        first.wait()
        serve()
        wait_until(lambda: http.get(f"/api/jobs/{job_id}").json()["state"] == "succeeded",
                   timeout_s=60)

    key = (data / "api-key").read_text().strip()
    said = log.read_text()
    assert f"API key: {key[:3]}…" in said and key not in said  # the key stays out of logs
    assert "superuser privileges" not in said  # Celery's warning, not for the embedded queue
    s = Settings(data_dir=data)
    rows = target_rows(s, job_id)
    for t in rows:
        assert [a.error_code for a in t.history].count(0) == 1, t.history  # one result each
    assert any(t.attempts == 2 for t in rows), "the kill met no target in flight"
    assert_files_exactly_once(s, MACHINES, FILES_PER_MACHINE)


def test_a_backup_job_whose_worker_is_killed_stores_every_file_once(
        crash_settings, add_machines, start_worker):
    s = crash_settings
    first = half_slow_fleet_to_back_up(s, add_machines, start_worker)
    with db.session_scope(s.resolved_database_url) as session:
        job_id = rollout.submit(
            session=session, settings=s, kind=JobKind.BACKUP, options=JobOptions(),
            targets=[service.TargetIn.parse({"machineID": f"m{m:03d}"})
                     for m in range(MACHINES)]).id
    wait_until(lambda: at_least(s, job_id, succeeded=2, running=3), timeout_s=30)

    first.kill()  # mid-job: some machines fetched, some fetching, some not started
    start_worker("b", s, pool="gevent")
    wait_until(lambda: finished(s, job_id) and stored_backup(s, job_id) is not None,
               timeout_s=60)

    assert any(t.attempts == 2 for t in target_rows(s, job_id)), "no fetch was interrupted"
    with db.session_scope(s.resolved_database_url) as session:
        backup = session.scalars(select(Backup).where(Backup.job_id == job_id)).one()
        assert backup.status is BackupStatus.COMPLETE
        assert manifests.verify(settings=s, backup=backup) == []  # every CRC and hash
    with zipfile.ZipFile(store.backup_dir(s) / backup.name) as archive:
        files = [n.split("/", 1)[1] for n in archive.namelist() if not n.endswith("/")]
    assert sorted(files) == sorted(
        [f"m{m:03d}_M{m}/B{f}.nc" for m in range(MACHINES) for f in range(FILES_PER_MACHINE)]
        + ["_manifest.json"])  # every file once, none twice after the rerun
    assert not list(store.backup_dir(s).glob(".*.part"))  # no temporary ZIP left
    assert not store.job_folder(s, job_id).exists()  # nor the fetched files


def test_a_backup_download_whose_worker_is_killed_is_whole_and_each_file_in_it_once(
        crash_settings, add_machines, start_worker):
    s = crash_settings
    first = half_slow_fleet_to_back_up(s, add_machines, start_worker)
    answer: dict[str, httpx.Response] = {}

    def download() -> None:
        with serving(create_app(s)) as live, httpx.Client(
                base_url=live.url, timeout=HTTP_TIMEOUT_S) as http:
            answer["it"] = http.post("/api/cnc/backupFiles", headers={"X-Api-Key": API_KEY},
                                     json=[{"machineID": f"m{m:03d}"} for m in range(MACHINES)])

    client = threading.Thread(target=download, name="download")
    client.start()
    wait_until(lambda: backup_job(s) is not None, timeout_s=30)
    job_id = backup_job(s)
    wait_until(lambda: at_least(s, job_id, succeeded=2, running=3), timeout_s=30)

    first.kill()  # mid-download: some machines fetched, some fetching, some not started
    start_worker("b", s, pool="gevent")
    client.join(timeout=90)

    assert any(t.attempts == 2 for t in target_rows(s, job_id)), "no fetch was interrupted"
    with zipfile.ZipFile(io.BytesIO(answer["it"].content)) as archive:
        assert archive.testzip() is None
        top = archive.namelist()[0]
        files = [n.removeprefix(top) for n in archive.namelist() if not n.endswith("/")]
        assert archive.read(f"{top}m003_M3/B0.nc") == PROGRAM * 4
    assert sorted(files) == sorted(
        [f"m{m:03d}_M{m}/B{f}.nc" for m in range(MACHINES) for f in range(FILES_PER_MACHINE)]
        + ["_manifest.json"])  # every file once, none twice after the rerun
    assert {t.state for t in target_rows(s, job_id)} == {TargetState.SUCCEEDED}
    assert not store.job_folder(s, job_id).exists()  # nor the fetched files


def half_slow_fleet_to_back_up(settings: Settings, add_machines: Any,
                               start_worker: Any) -> WorkerProcess:
    """MACHINES mock machines with FILES_PER_MACHINE programs each, half the fleet slow (five
    operations of 0.8 s) so that a kill finds fetches going on; and a gevent worker "a",
    ready."""
    add_machines(*({**m, "options": {"latency_ms": 50 if i < MACHINES // 2 else 800}}
                   for i, m in enumerate(fleet(MACHINES))))
    for m in range(MACHINES):
        for f in range(FILES_PER_MACHINE):
            on_machine(settings, f"m{m:03d}", f"B{f}.nc").write_bytes(PROGRAM * (m + 1))
    worker = start_worker("a", settings, pool="gevent")
    worker.wait_ready()
    return worker


def backup_job(settings: Settings) -> str | None:
    """The backup job a backupFiles request made, once it is made."""
    with db.session_scope(settings.resolved_database_url) as session:
        return session.scalar(select(Job.id).where(Job.kind == JobKind.BACKUP))


def test_a_send_rerun_after_a_crash_that_finds_its_own_bytes_counts_as_done(
        settings, add_machines):
    add_machines(*fleet(1))
    job_id = create(settings, [{"machineID": "m000", "fileName": "P.nc"}])
    first, _ = claim(settings, job_id, lease_s=0.0)
    with files_of(settings, "m000") as files:
        assert operations.execute(settings, files, first).error is None  # the bytes got there ...
    lose_the_worker(settings)  # ... and the worker died before recording it
    again, holder = claim(settings, job_id)
    with files_of(settings, "m000") as files:
        outcome = operations.execute(settings, files, again)
    runs.finish(settings=settings, work=again, holder=holder, error=outcome.error,
                state=outcome.state, status_msg=outcome.status_msg)

    assert (first.attempt, again.attempt, again.previous_interrupted) == (1, 2, True)
    assert outcome.error is None
    [t] = target_rows(settings, job_id)
    assert (t.state, t.error_code) == (TargetState.SUCCEEDED, 0)
    assert [(a.number, a.error_code) for a in t.history] == [(1, None), (2, 0)]
    assert machine_file(settings, "m000", "P.nc").read_bytes() == PROGRAM


def rerun_a_replacing_send_after_a_crash(settings, add_machines, *,
                                         left_there: bytes | None = None):
    """A replacing send of P.nc over "the old program" whose first attempt replaced it and
    whose worker died before recording that; the machine's file then holds `left_there` (if
    given), and a second attempt runs to its end. Its target, and the machine's file."""
    add_machines(*fleet(1))
    existing = machine_file(settings, "m000", "P.nc")
    existing.parent.mkdir(parents=True, exist_ok=True)
    existing.write_bytes(b"the old program\n")
    job_id = create(settings, [{"machineID": "m000", "fileName": "P.nc"}],
                    options=JobOptions(replace=True))
    first, _ = claim(settings, job_id, lease_s=0.0)
    with files_of(settings, "m000") as files:
        assert operations.execute(settings, files, first).error is None  # replaced ...
    lose_the_worker(settings)  # ... and the worker died before recording it
    if left_there is not None:
        existing.write_bytes(left_there)
    again, holder = claim(settings, job_id)
    with files_of(settings, "m000") as files:
        outcome = operations.execute(settings, files, again)
    runs.finish(settings=settings, work=again, holder=holder, error=outcome.error,
                state=outcome.state, status_msg=outcome.status_msg,
                replaced_payload_id=outcome.replaced_payload_id)
    [t] = target_rows(settings, job_id)
    return t, existing


def kept_copy(settings, target) -> bytes:
    with db.session_scope(settings.resolved_database_url) as session:
        return session.get(Payload, target.replaced_payload_id).data


def test_a_replacing_send_rerun_after_a_crash_that_finds_its_own_bytes_says_it_replaced(
        settings, add_machines):
    t, existing = rerun_a_replacing_send_after_a_crash(settings, add_machines)

    assert (t.state, t.status_msg) == (TargetState.SUCCEEDED,
                                       "replaced; the old file is kept with the job")
    assert kept_copy(settings, t) == b"the old program\n"
    assert existing.read_bytes() == PROGRAM


def test_a_replacing_send_rerun_over_what_its_first_attempt_wrote_keeps_the_first_copy(
        settings, add_machines):
    # The rerun kept the file the first attempt had written (here read back wrong) as "the
    # old file": restore-replaced then put that back, and the program the job replaced was lost.
    t, existing = rerun_a_replacing_send_after_a_crash(
        settings, add_machines, left_there=b"what the first attempt left, damaged\n")

    assert t.state is TargetState.SUCCEEDED and existing.read_bytes() == PROGRAM
    assert kept_copy(settings, t) == b"the old program\n"


def test_a_first_send_that_finds_the_same_bytes_already_there_answers_142(
        settings, add_machines):
    add_machines(*fleet(1))
    existing = machine_file(settings, "m000", "P.nc")
    existing.parent.mkdir(parents=True, exist_ok=True)
    existing.write_bytes(PROGRAM)  # put there by someone else, not by an attempt of this job
    job_id = create(settings, [{"machineID": "m000", "fileName": "P.nc"}])
    work, _ = claim(settings, job_id)
    with files_of(settings, "m000") as files, pytest.raises(ContractError) as caught:
        operations.execute(settings, files, work)
    assert (work.attempt, caught.value.code) == (1, ErrorCode.PATH_EXISTS)


def test_a_retry_after_142_that_finds_the_same_bytes_answers_142_again(settings, add_machines):
    add_machines(*fleet(1))
    existing = machine_file(settings, "m000", "P.nc")
    existing.parent.mkdir(parents=True, exist_ok=True)
    existing.write_bytes(PROGRAM)  # another job's copy of the same program
    job_id = create(settings, [{"machineID": "m000", "fileName": "P.nc"}])
    first, holder = claim(settings, job_id)
    with files_of(settings, "m000") as files, pytest.raises(ContractError) as caught:
        operations.execute(settings, files, first)
    runs.finish(settings=settings, work=first, holder=holder, error=caught.value)
    with db.session_scope(settings.resolved_database_url) as session:
        assert service.retry_failed(session=session, job_id=job_id) == 1

    again, _ = claim(settings, job_id)
    with files_of(settings, "m000") as files, pytest.raises(ContractError) as caught_again:
        operations.execute(settings, files, again)
    assert (again.attempt, caught_again.value.code) == (2, ErrorCode.PATH_EXISTS)


def test_a_retry_after_a_dropped_connection_that_finds_its_bytes_counts_as_done(
        settings, add_machines):
    add_machines(*fleet(1))
    job_id = create(settings, [{"machineID": "m000", "fileName": "P.nc"}])
    first, holder = claim(settings, job_id)
    with files_of(settings, "m000") as files:
        assert operations.execute(settings, files, first).error is None  # the bytes got there,
    dropped = ContractError(ErrorCode.CONNECTION_FAILED, "connection dropped")  # the reply not
    runs.finish(settings=settings.model_copy(update={"retry_base_s": 0.0}), work=first,
                holder=holder, error=dropped)

    again, _ = claim(settings, job_id)
    with files_of(settings, "m000") as files:
        outcome = operations.execute(settings, files, again)
    # A dropped connection is a cut-off attempt: remembered as one (Target.interrupted).
    assert (again.attempt, again.previous_interrupted, outcome.error) == (2, True, None)
    assert outcome.status_msg == "file already there from an earlier attempt"


def test_a_retry_after_the_machine_was_offline_that_finds_the_same_bytes_answers_142(
        settings, add_machines):
    # An offline machine refused the first attempt before anything was sent: the same bytes
    # found later were put there by someone else, not by this target.
    add_machines(*fleet(1))
    existing = machine_file(settings, "m000", "P.nc")
    existing.parent.mkdir(parents=True, exist_ok=True)
    existing.write_bytes(PROGRAM)
    job_id = create(settings, [{"machineID": "m000", "fileName": "P.nc"}])
    first, holder = claim(settings, job_id)
    runs.finish(settings=settings.model_copy(update={"retry_base_s": 0.0}), work=first,
                holder=holder, error=ContractError(ErrorCode.MACHINE_OFFLINE))

    again, _ = claim(settings, job_id)
    with files_of(settings, "m000") as files, pytest.raises(ContractError) as caught:
        operations.execute(settings, files, again)
    assert (again.attempt, caught.value.code) == (2, ErrorCode.PATH_EXISTS)


def test_a_send_rerun_that_finds_other_bytes_answers_142_and_leaves_them(
        settings, add_machines):
    add_machines(*fleet(1))
    existing = machine_file(settings, "m000", "P.nc")
    existing.parent.mkdir(parents=True, exist_ok=True)
    existing.write_bytes(b"someone else's program\n")
    job_id = create(settings, [{"machineID": "m000", "fileName": "P.nc"}])
    claim(settings, job_id, lease_s=0.0)  # a first attempt, lost with its worker
    lose_the_worker(settings)
    work, _ = claim(settings, job_id)
    with files_of(settings, "m000") as files, pytest.raises(ContractError) as caught:
        operations.execute(settings, files, work)
    assert (work.attempt, caught.value.code) == (2, ErrorCode.PATH_EXISTS)
    assert existing.read_bytes() == b"someone else's program\n"


# -- helpers ---------------------------------------------------------------------------


def fleet(n: int, **options: Any) -> list[dict[str, Any]]:
    return [{"id": f"m{i:03d}", "name": f"M{i}", "model": "Mock", "options": dict(options)}
            for i in range(n)]


def targets(machines_n: int, files_per_machine: int) -> list[dict[str, Any]]:
    """Every machine gets P0..P<n-1>.nc; positions go round the machines."""
    return [{"machineID": f"m{m:03d}", "fileName": f"P{f}.nc"}
            for f in range(files_per_machine) for m in range(machines_n)]


def register(settings: Settings, entries: list[dict[str, Any]]) -> None:
    from jobs.fleet import fleet_file, registry

    with db.session_scope(settings.resolved_database_url) as session:
        fleet_file.import_fleet(session=session, data_dir=settings.data_dir,
                                machines=[registry.MachineIn.model_validate(e) for e in entries])


def create(settings: Settings, raw_targets: list[dict[str, Any]],
           options: JobOptions | None = None) -> str:
    """A send job of PROGRAM, recorded but not queued."""
    with db.session_scope(settings.resolved_database_url) as session:
        payload_id = service.store_payload(session=session, data=PROGRAM)
        return service.create(session=session, kind=JobKind.SEND,
                              targets=[service.TargetIn.parse(t) for t in raw_targets],
                              options=options, payload_id=payload_id).id


def submit(settings: Settings, raw_targets: list[dict[str, Any]]) -> str:
    """A send job of PROGRAM, recorded and queued as the API does it."""
    with db.session_scope(settings.resolved_database_url) as session:
        payload_id = service.store_payload(session=session, data=PROGRAM)
        return rollout.submit(session=session, settings=settings, kind=JobKind.SEND,
                              targets=[service.TargetIn.parse(t) for t in raw_targets],
                              options=JobOptions(), payload_id=payload_id).id


def claim(settings: Settings, job_id: str, lease_s: float = 30.0) -> tuple[runs.Work, str]:
    """The machine's slot and its first due target, as a runner takes them."""
    started = runs.begin(settings=settings.model_copy(update={"lease_ttl_s": lease_s}),
                         job_id=job_id, machine_id="m000")
    assert started.work is not None and started.holder is not None
    return started.work, started.holder


def files_of(settings: Settings, machine_id: str) -> Any:
    from jobs.fleet import door, registry

    with db.session_scope(settings.resolved_database_url) as session:
        spec = registry.get(session=session, machine_id=machine_id)
    return door.open_files(spec, data_dir=settings.data_dir)


def lose_the_worker(settings: Settings) -> None:
    """The reaper's pass after a worker died: its expired attempt is marked interrupted."""
    # No broker configured: the reaper's requeue goes to the file queue in the data folder.
    wait_until(lambda: reaper.reap(settings=settings) >= 1, timeout_s=10)


def machine_file(settings: Settings, machine_id: str, name: str) -> Path:
    return settings.data_dir / "mock" / machine_id / "files" / name


def target_rows(settings: Settings, job_id: str) -> list[Target]:
    with db.session_scope(settings.resolved_database_url) as session:
        return list(session.scalars(select(Target).where(Target.job_id == job_id)
                                    .options(selectinload(Target.history))
                                    .order_by(Target.position)))


def workers(target: Target) -> list[str]:
    return [a.worker for a in target.history]


def at_least(settings: Settings, job_id: str, **states: int) -> bool:
    with db.session_scope(settings.resolved_database_url) as session:
        found = settle.counts(session=session, job_id=job_id)
    return all(found[state] >= n for state, n in states.items())


def finished(settings: Settings, job_id: str) -> bool:
    with db.session_scope(settings.resolved_database_url) as session:
        return settle.is_finished(session=session, job_id=job_id)


def machines_not_started(settings: Settings, job_id: str) -> set[str]:
    rows = target_rows(settings, job_id)
    started = {t.machine_id for t in rows if t.state is not TargetState.PENDING}
    return {t.machine_id for t in rows} - started


def part_files(settings: Settings) -> list[Path]:
    return list((settings.data_dir / "mock").glob(f"*/files/**/{PART_PREFIX}*"))


def kill_between_writes(worker: WorkerProcess, settings: Settings,
                        job_id: str) -> dict[int, TargetState]:
    """SIGKILL the worker at a moment no write has a temporary file open; the states then.

    A kill inside a write's few milliseconds between temporary file and rename would
    leave a `.dncq-part-*` file on the mock until a later write sweeps it; this test is
    about the queue and the database, so it stops the worker (SIGSTOP) outside that window.
    The states are read once it is dead: a worker stopped inside a SQLite commit (its log
    written, the shared index not yet) shows the commit only to the reads after it died.
    """
    for _ in range(100):
        os.kill(worker.pid, signal.SIGSTOP)
        if not part_files(settings):
            break
        os.kill(worker.pid, signal.SIGCONT)
        time.sleep(0.005)
    else:
        worker.kill()
        raise AssertionError("the worker was always in the middle of a write")
    worker.kill()
    return {t.id: t.state for t in target_rows(settings, job_id)}  # nothing changes them now


def assert_files_exactly_once(settings: Settings, machines_n: int, files_per_machine: int) -> None:
    """Each machine holds its files with PROGRAM in them, nothing else (no temporary files)."""
    for m in range(machines_n):
        folder = settings.data_dir / "mock" / f"m{m:03d}" / "files"
        assert sorted(p.name for p in folder.iterdir()) \
            == [f"P{f}.nc" for f in range(files_per_machine)], folder
        for f in range(files_per_machine):
            assert (folder / f"P{f}.nc").read_bytes() == PROGRAM


def stored_backup(settings: Settings, job_id: str) -> Backup | None:
    with db.session_scope(settings.resolved_database_url) as session:
        return session.scalars(select(Backup).where(Backup.job_id == job_id)).first()
