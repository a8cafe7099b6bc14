"""backupFiles' download while the workers fetch its job: faults on the way, a client that
goes away, and no worker at all. (A worker killed mid-download: tests/jobs/run/test_crash.py.)"""

from __future__ import annotations

import io
import os
import socket
import zipfile
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from jobs import db
from jobs.api.app import create_app
from jobs.backup import download, store
from jobs.errors import from_transport
from jobs.folders import job_folder
from jobs.models import Attempt, Job, Target, TargetState
from jobs.run import leases
from tests.conftest import API_KEY
from tests.jobs.helpers import at_once, mock_file, mock_of, on_machine, wait_until
from tests.live_server import HTTP_TIMEOUT_S, serving
from worker.transports.base import Dropped

MACHINES = [{"id": f"b{i}", "name": f"B{i}", "model": "Mock"} for i in range(3)]


@pytest.fixture
def fleet(queue_settings: Any, add_machines: Any) -> list[str]:
    """Three mock machines with two programs each."""
    add_machines(*MACHINES)
    for machine in MACHINES:
        for n in range(2):
            mock_file(queue_settings, machine["id"], f"P{n}.nc", f"G0 X{n} ({machine['id']})\n")
    return [m["id"] for m in MACHINES]


def slow_down(settings: Any, machine_ids: list[str], *, latency_ms: float) -> None:
    for machine_id in machine_ids:
        mock_of(settings, machine_id).set_options(latency_ms=latency_ms)


def body(machine_ids: list[str]) -> list[dict[str, str]]:
    return [{"machineID": m} for m in machine_ids]


def job_states(settings: Any, job_id: str) -> tuple[str, list[TargetState]]:
    with db.session_scope(settings.resolved_database_url) as session:
        job = session.get(Job, job_id)
        assert job is not None
        states = list(session.scalars(select(Target.state).where(Target.job_id == job_id)
                                      .order_by(Target.position)))
        return job.state.value, states


def job_story(settings: Any, job_id: str) -> list[tuple[Any, ...]]:
    """Each target's machine, state and error with its attempts: what a failed wait shows."""
    with db.session_scope(settings.resolved_database_url) as session:
        targets = session.scalars(select(Target).where(Target.job_id == job_id)
                                  .order_by(Target.position)).all()
        return [(t.machine_id, t.state.value, t.error_code, t.error_msg,
                 [(a.number, a.error_code, a.error_msg) for a in session.scalars(
                     select(Attempt).where(Attempt.target_id == t.id))]) for t in targets]


def test_a_dropped_connection_is_retried_and_the_download_is_whole(
        queue_client, queue_settings, fleet, monkeypatch):
    real_fetch = store.fetch_target
    dropped: list[str] = []

    def fetch(settings_, files, *, machine_id, **kwargs):
        if machine_id == "b1" and not dropped:
            dropped.append(machine_id)
            raise from_transport(Dropped("connection dropped mid-transfer"))
        return real_fetch(settings_, files, machine_id=machine_id, **kwargs)

    monkeypatch.setattr(store, "fetch_target", fetch)  # in the worker, which is in-process

    response = queue_client.post("/api/cnc/backupFiles", json=body(fleet))

    archive = zipfile.ZipFile(io.BytesIO(response.content))
    assert archive.testzip() is None
    top = archive.namelist()[0]
    assert archive.read(f"{top}b1_B1/P1.nc") == b"G0 X1 (b1)\n"
    assert dropped == ["b1"]
    job_id = response.headers["X-Dncq-Job"]
    with TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as client:
        detail = client.get(f"/api/jobs/{job_id}").json()
    assert detail["state"] == "succeeded"
    assert [t["attempts"] for t in detail["targets"]] == [1, 2, 1]


def test_a_client_that_goes_away_leaves_a_cancelled_job_and_no_files(
        queue_settings, celery_worker, fleet):
    # The first machine's files are more than the download's first piece: the answer has
    # begun while the others are still read.
    mock_file(queue_settings, fleet[0], "BIG.nc", os.urandom(download.SENT_BYTES).hex())
    slow_down(queue_settings, fleet[1:], latency_ms=300)
    with serving(create_app(queue_settings)) as live, httpx.Client(
            base_url=live.url, timeout=HTTP_TIMEOUT_S) as http:
        with http.stream("POST", "/api/cnc/backupFiles", json=body(fleet),
                         headers={"X-Api-Key": API_KEY}) as response:
            assert response.status_code == 200
            job_id = response.headers["X-Dncq-Job"]
        # the client hangs up while the machines are still read (noticed at the next piece)
        live.wait_idle()

    wait_until(lambda: job_states(queue_settings, job_id)[0] == "cancelled", timeout_s=30)
    wait_until(lambda: TargetState.RUNNING not in job_states(queue_settings, job_id)[1],
               timeout_s=30)
    # A target still running when the client left finishes; the reaper removes its files.
    wait_until(lambda: not job_folder(queue_settings, job_id).exists(), timeout_s=30)
    assert TargetState.PENDING not in job_states(queue_settings, job_id)[1]


def test_a_client_that_goes_away_after_every_machine_was_fetched_leaves_a_cancelled_job(
        queue_settings, celery_worker, fleet):
    # Every machine fetched, the job succeeded while its ZIP is still on its way: the
    # client hanging up must turn it cancelled with the answer's end, not whenever the
    # garbage collector finds the download's generator (a minute and more). On its way:
    # more than the socket's buffers hold, with the client's kept small (no autotuning).
    for machine_id in fleet:
        on_machine(queue_settings, machine_id, "BIG.nc").write_bytes(
            os.urandom(8 * download.SENT_BYTES))  # no deflate makes it smaller
    small_window = httpx.HTTPTransport(
        socket_options=[(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 * 1024)])
    with serving(create_app(queue_settings)) as live, httpx.Client(
            base_url=live.url, timeout=HTTP_TIMEOUT_S, transport=small_window) as http:
        with http.stream("POST", "/api/cnc/backupFiles", json=body(fleet),
                         headers={"X-Api-Key": API_KEY}) as response:
            job_id = response.headers["X-Dncq-Job"]
            pieces = response.iter_raw()  # held: an iterator dropped closes the connection
            next(pieces)
            # The workers' fetch of three machines, on a host loaded by the whole suite, once
            # took longer than the default 30 s wait.
            wait_until(lambda: job_states(queue_settings, job_id)[0] == "succeeded",
                       timeout_s=90, describe=lambda: job_story(queue_settings, job_id))
        live.wait_idle()  # the answer is over

        state, targets = job_states(queue_settings, job_id)

    assert (state, set(targets)) == ("cancelled", {TargetState.CANCELLED})
    assert not job_folder(queue_settings, job_id).exists()


def test_a_client_that_reads_slowly_gets_the_whole_zip_after_the_reaper_looked_at_the_job(
        queue_settings, celery_worker, fleet):
    # The job ends with its last machine fetched; a client still reading the ZIP then got a
    # broken one, since the reaper removed the work files of a finished streamed job that
    # the download had not reached yet ("No such file or directory: …/2.spool").
    from datetime import timedelta

    from jobs.models import utcnow
    from jobs.run import reaper

    for machine_id in fleet:  # more than the socket's buffers hold
        mock_file(queue_settings, machine_id, "BIG.nc", os.urandom(2 * 1024 * 1024).hex())
    with serving(create_app(queue_settings)) as live, httpx.Client(
            base_url=live.url, timeout=HTTP_TIMEOUT_S) as http:
        with http.stream("POST", "/api/cnc/backupFiles", json=body(fleet),
                         headers={"X-Api-Key": API_KEY}) as response:
            pieces = response.iter_raw()
            data = next(pieces)
            job_id = response.headers["X-Dncq-Job"]
            wait_until(lambda: job_states(queue_settings, job_id)[0] == "succeeded",
                       timeout_s=90, describe=lambda: job_story(queue_settings, job_id))
            reaper._assemble_forgotten_backups(queue_settings, utcnow() + timedelta(minutes=1))
            data += b"".join(pieces)

    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        assert archive.testzip() is None
        assert sum(n.endswith("BIG.nc") for n in archive.namelist()) == len(fleet)
    wait_until(lambda: not job_folder(queue_settings, job_id).exists())  # removed once sent


def test_with_no_worker_the_download_answers_why_before_its_first_byte(settings, fleet, caplog):
    quick = settings.model_copy(update={"batch_wait_s": 0.5})
    with serving(create_app(quick)) as live, httpx.Client(
            base_url=live.url, timeout=HTTP_TIMEOUT_S) as http:
        response = http.post("/api/cnc/backupFiles", json=body(fleet),
                             headers={"X-Api-Key": API_KEY})
        live.wait_idle()

    assert response.status_code == 200 and response.json()["errorCode"] == 20005
    assert "is a worker running?" in response.json()["statusMsg"]
    assert "is a worker running?" in caplog.text
    with db.session_scope(settings.resolved_database_url) as session:
        [job_id] = session.scalars(select(Job.id))
    state, targets = job_states(settings, job_id)
    assert (state, set(targets)) == ("cancelled", {TargetState.CANCELLED})
    assert not job_folder(settings, job_id).exists()


def test_two_downloads_of_the_same_machines_at_once_are_whole_one_operation_at_a_time(
        queue_settings, celery_worker, fleet):
    slow_down(queue_settings, fleet, latency_ms=50)
    with serving(create_app(queue_settings)) as live, httpx.Client(
            base_url=live.url, timeout=HTTP_TIMEOUT_S) as http:

        def download() -> bytes:
            return http.post("/api/cnc/backupFiles", json=body(fleet),
                             headers={"X-Api-Key": API_KEY}).content

        answers = at_once(download, download)

    listings = []
    for answer in answers:
        archive = zipfile.ZipFile(io.BytesIO(answer))
        assert archive.testzip() is None
        top = archive.namelist()[0]
        listings.append(sorted(n.removeprefix(top) for n in archive.namelist()))
    assert listings[0] == listings[1] and "b2_B2/P1.nc" in listings[0]
    assert [mock_of(queue_settings, m).peak_active() for m in fleet] == [1, 1, 1]


def test_a_machine_busy_past_busy_wait_s_answers_20007_before_any_byte(
        queue_settings, celery_worker, fleet):
    quick = queue_settings.model_copy(update={"busy_wait_s": 0.3})
    url = queue_settings.resolved_database_url
    with TestClient(create_app(quick), headers={"X-Api-Key": API_KEY}) as client:
        with leases.hold(url, machine_id="b1", max_concurrent=1, wait_s=0):  # another's slot
            busy = client.post("/api/cnc/backupFiles", json=body(fleet))
        after = client.post("/api/cnc/backupFiles", json=body(fleet))

    assert busy.json()["errorCode"] == 20007 and "(b1: root)" in busy.json()["statusMsg"]
    assert zipfile.ZipFile(io.BytesIO(after.content)).testzip() is None
    assert [mock_of(queue_settings, m).peak_active() for m in fleet] == [1, 1, 1]
