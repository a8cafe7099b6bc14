"""Distributed mode: PostgreSQL, Redis, the API and two `dncq worker` processes."""

from __future__ import annotations

import hashlib
import random
import zipfile
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr
from sqlalchemy import select

from jobs import db
from jobs.api.app import create_app
from jobs.backup import store
from jobs.fleet import registry
from jobs.models import Attempt, Target
from jobs.settings import AuthMode, Settings
from tests.conftest import API_KEY
from tests.jobs.helpers import mock_file, mock_of, run_backup
from worker.transports import mock_state

pytestmark = pytest.mark.slow

PROGRAM = "G21 G90\nG0 X0 Y0\nG1 X10 F100\nM30\n"
MACHINES = 50
FILES_PER_MACHINE = 4


@pytest.fixture
def distributed_settings(tmp_path: Path, postgres_url: str, redis_server: Any) -> Settings:
    """PostgreSQL as the database, Redis as the queue; the data folder holds the mocks."""
    redis_server.flush()
    data = tmp_path / "data"
    data.mkdir()
    # No periodic machine checks: a worker's first one comes 5 s after it starts, and on a
    # loaded host it met a batch still running, an operation beside the pool's that the
    # tests counting operations at once would count too.
    return Settings(data_dir=data, database_url=postgres_url, broker_url=redis_server.url,
                    api_key=SecretStr(API_KEY), auth=AuthMode.KEY, reaper_interval_s=0.5,
                    batch_wait_s=90.0, machine_check_interval_s=0)


@pytest.mark.parametrize("pool", ["threads", "gevent"])
def test_two_workers_share_a_200_target_batch_and_keep_one_operation_per_machine(
        distributed_settings, start_worker, pool):
    s = distributed_settings
    with db.session_scope(s.resolved_database_url) as session:
        for i in range(MACHINES):
            registry.upsert(session=session, data_dir=s.data_dir,
                            machine_in=registry.MachineIn(
                id=f"d{i:03d}", name=f"D{i}", model="Mock", options={"latency_ms": 20}))
    targets = [{"machineID": f"d{m:03d}", "fileName": f"P{f}.nc"}
               for m in range(MACHINES) for f in range(FILES_PER_MACHINE)]
    random.Random(7).shuffle(targets)  # request order is neither by machine nor by file
    workers = [start_worker(name, s, concurrency=16, pool=pool) for name in ("w1", "w2")]
    for worker in workers:
        worker.wait_ready()  # both consume before the tasks arrive

    with TestClient(create_app(s), headers={"X-Api-Key": API_KEY}) as client:
        response = client.post("/api/cnc/batchSendFile",
                               json={"content": PROGRAM, "targets": targets})
        assert response.status_code == 200
        job = client.get(f"/api/jobs/{response.headers['X-Dncq-Job']}").json()

    assert response.json() == [{"errorCode": 0, "errorMsg": "Success"}] * len(targets)
    assert [{"machineID": t["machineID"], "fileName": t["fileName"]} for t in job["targets"]] \
        == targets
    for t in targets:
        path = s.data_dir / "mock" / t["machineID"] / "files" / t["fileName"]
        assert path.read_text() == PROGRAM
    with db.session_scope(s.resolved_database_url) as session:
        signed = set(session.scalars(select(Attempt.worker).join(Target)
                                     .where(Target.job_id == job["id"])))
    assert signed == {w.worker_name for w in workers}
    assert {m: mock_of(s, f"d{m:03d}").peak_active() for m in range(MACHINES)} \
        == {m: 1 for m in range(MACHINES)}
    for worker in workers:  # every task acknowledged: none is delivered a second time later
        assert "Couldn't ack" not in worker.log()


def test_a_gevent_worker_stores_a_backup_that_verifies(distributed_settings, start_worker):
    s = distributed_settings
    with db.session_scope(s.resolved_database_url) as session:
        for i in range(10):
            registry.upsert(session=session, data_dir=s.data_dir,
                            machine_in=registry.MachineIn(
                id=f"g{i:02d}", name=f"G{i}", model="Mock", options={"latency_ms": 5}))
    for i in range(10):
        for f in range(5):
            mock_file(s, f"g{i:02d}", f"sub/P{f}.nc", f"G0 X{i} Y{f}\n" * 3000)
    mock_file(s, "g03", "sub/Teil ü 1.nc", "G0 X3\n")  # COPY's text format escapes these
    start_worker("g", s, concurrency=16, pool="gevent").wait_ready()

    with TestClient(create_app(s), headers={"X-Api-Key": API_KEY}) as client:
        backup = run_backup(client, machines={"all": True})
        verified = client.post(f"/api/backups/{backup['id']}/verify").json()
        recorded = client.get(f"/api/backups/{backup['id']}/manifest").json()["files"]

    assert (backup["status"], backup["files"]) == ("complete", 51)
    assert verified["ok"], verified["problems"]
    with zipfile.ZipFile(store.backup_dir(s) / backup["name"]) as archive:
        top = archive.namelist()[0]
        assert archive.read(f"{top}g07_G7/sub/P3.nc") == b"G0 X7 Y3\n" * 3000
        in_zip = {name: archive.read(name) for name in archive.namelist()
                  if name.endswith(".nc")}
    # The database's record, file by file (PostgreSQL takes the rows by COPY).
    assert sorted(f["archivePath"] for f in recorded) == sorted(in_zip)
    for f in recorded:
        data, name = in_zip[f["archivePath"]], f["archivePath"].rsplit("/", 1)[1]
        assert f["archivePath"].startswith(f"{top}{f['machineID']}_")
        assert f["path"].endswith(f"sub/{name}")
        assert (f["size"], f["sha256"]) == (len(data), hashlib.sha256(data).hexdigest())
        assert f["mtime"] > 0


def test_a_64_slot_gevent_worker_acknowledges_every_task(distributed_settings, start_worker):
    s = distributed_settings
    ids = [f"e{i:03d}" for i in range(200)]
    with db.session_scope(s.resolved_database_url) as session:
        for machine_id in ids:
            registry.upsert(session=session, data_dir=s.data_dir,
                            machine_in=registry.MachineIn(
                id=machine_id, name=machine_id, model="Mock", options={"latency_ms": 50}))
    worker = start_worker("e", s, concurrency=64, pool="gevent")
    worker.wait_ready()

    with TestClient(create_app(s), headers={"X-Api-Key": API_KEY}) as client:
        response = client.post("/api/cnc/batchSendFile", json={
            "content": PROGRAM, "targets": [{"machineID": m, "fileName": "O1.nc"} for m in ids]})

    assert response.json() == [{"errorCode": 0, "errorMsg": "Success"}] * len(ids)
    # 64 tasks ending together ack at once; an ack that finds no Redis connection free
    # leaves its task to be delivered again hours later.
    assert "Couldn't ack" not in worker.log()


@pytest.mark.parametrize("claim_ahead", [True, False])
def test_a_gevent_worker_runs_as_many_machine_operations_at_once_as_its_concurrency(
        distributed_settings, start_worker, claim_ahead):
    # Its pool holds twice as many tasks: the others claim their targets while they wait
    # for a slot, so that a slot that frees starts the next operation at once.
    s = distributed_settings.model_copy(update={"claim_ahead": claim_ahead})
    ids = [f"c{i:02d}" for i in range(12)]
    with db.session_scope(s.resolved_database_url) as session:
        for machine_id in ids:
            registry.upsert(session=session, data_dir=s.data_dir,
                            machine_in=registry.MachineIn(
                id=machine_id, name=machine_id, model="Mock",
                options={"latency_ms": 300, "trace": True}))
    start_worker("c", s, concurrency=3, pool="gevent").wait_ready()

    with TestClient(create_app(s), headers={"X-Api-Key": API_KEY}) as client:
        response = client.post("/api/cnc/batchSendFile", json={
            "content": PROGRAM, "targets": [{"machineID": m, "fileName": "O1.nc"} for m in ids]})
        job = client.get(f"/api/jobs/{response.headers['X-Dncq-Job']}").json()

    assert response.json() == [{"errorCode": 0, "errorMsg": "Success"}] * len(ids)
    assert mock_state.most_at_once(mock_state.traced([s.data_dir / "mock" / m for m in ids])) == 3
    when = datetime.fromisoformat
    most_claimed = mock_state.most_at_once((when(t["startedAt"]), when(t["finishedAt"]))
                                           for t in job["targets"])
    assert most_claimed > 3 if claim_ahead else most_claimed <= 3
