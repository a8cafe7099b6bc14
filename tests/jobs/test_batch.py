"""Batch rollout and delete on a real Redis queue and a real Celery worker."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from typing import Any

import httpx
import pytest
from sqlalchemy import update

from jobs import db, job_views
from jobs.api.app import create_app
from jobs.models import Target, TargetState
from tests.conftest import API_KEY
from tests.jobs.helpers import at_once, mock_file, mock_of, on_machine, wait_done, wait_until
from tests.live_server import HTTP_TIMEOUT_S, serving
from worker.transports.base import Dropped

PROGRAM = "G21 G90\nG0 X0 Y0\nM30\n"


def mocks(n: int, **options: Any) -> list[dict[str, Any]]:
    return [{"id": f"m{i:03d}", "name": f"M{i}", "model": "Mock", "options": dict(options)}
            for i in range(n)]


def test_batch_send_keeps_request_order_when_targets_finish_out_of_order(
        queue_client, add_machines, queue_settings):
    # The first machine is slowest by far, so its result is recorded last.
    add_machines(*[{"id": f"s{i}", "name": f"S{i}", "model": "Mock",
                    "options": {"latency_ms": 1500 if i == 0 else 60}} for i in range(5)])
    targets = [{"machineID": f"s{i}", "fileName": f"P{i}.nc"} for i in range(5)]
    targets.insert(2, {"machineID": "nope", "fileName": "x.nc"})
    response = queue_client.post("/api/cnc/batchSendFile",
                                 json={"content": PROGRAM, "targets": targets})
    assert response.status_code == 200
    body = response.json()
    assert [r["errorCode"] for r in body] == [0, 0, 10003, 0, 0, 0]
    job = queue_client.get(f"/api/jobs/{response.headers['X-Dncq-Job']}").json()
    finished = {t["machineID"]: t["finishedAt"] for t in job["targets"] if t["finishedAt"]}
    assert finished["s0"] > finished["s4"]  # s0 really did finish after s4
    for i in range(5):
        assert (queue_settings.data_dir / "mock" / f"s{i}" / "files" / f"P{i}.nc").read_text() \
            == PROGRAM


def test_batch_send_reports_142_for_an_existing_file_and_leaves_it_unchanged(
        queue_client, add_machines, queue_settings):
    add_machines(*mocks(2))
    existing = queue_settings.data_dir / "mock" / "m001" / "files" / "P.nc"
    existing.parent.mkdir(parents=True, exist_ok=True)
    existing.write_text("old")
    body = queue_client.post("/api/cnc/batchSendFile", json={
        "content": PROGRAM,
        "targets": [{"machineID": "m000", "fileName": "P.nc"},
                    {"machineID": "m001", "fileName": "P.nc"}]}).json()
    assert body == [{"errorCode": 0, "errorMsg": "Success"},
                    {"errorCode": 142, "errorMsg": "Path exists."}]
    assert existing.read_text() == "old"


def test_a_batch_targets_machine_and_file_written_as_numbers_are_taken_as_their_names(
        queue_client, add_machines, queue_settings):
    # A client that keeps ids and Fanuc program numbers as numbers: it got 20001.
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    body = queue_client.post("/api/cnc/batchSendFile", json={
        "content": PROGRAM, "targets": [{"machineID": 1010, "fileName": 8001}]}).json()

    assert body == [{"errorCode": 0, "errorMsg": "Success"}]
    assert (queue_settings.data_dir / "mock" / "1010" / "files" / "8001").read_text() == PROGRAM


def test_batch_delete_returns_results_in_order(queue_client, add_machines, queue_settings):
    add_machines(*mocks(2))
    for machine in ("m000", "m001"):
        path = queue_settings.data_dir / "mock" / machine / "files" / "P.nc"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(PROGRAM)
    body = queue_client.post("/api/cnc/batchDeleteFile", json=[
        {"machineID": "m000", "fileName": "P.nc"},
        {"machineID": "m009", "fileName": "P.nc"},
        {"machineID": "m001", "fileName": "missing.nc"},
        {"machineID": "m001", "fileName": "P.nc"}]).json()
    assert [r["errorCode"] for r in body] == [0, 10003, 158, 0]
    assert not (queue_settings.data_dir / "mock" / "m000" / "files" / "P.nc").exists()


def test_batch_send_refuses_a_program_in_a_locked_range_and_sends_it_to_the_other_machines(
        queue_client, add_machines):
    add_machines(*[{"id": m, "name": m, "model": "Fanuc 0i-F"} for m in ("locked", "free")])
    assert queue_client.get("/api/cnc/lockFileByRange", params={
        "machineID": "locked", "isLock": "true", "lockStart": 9000, "lockEnd": 9999,
    }).json()["errorCode"] == 0
    response = queue_client.post("/api/cnc/batchSendFile", json={
        "content": "%\nO9001\nM30\n%\n",
        "targets": [{"machineID": "locked"}, {"machineID": "free"}]})
    assert [r["errorCode"] for r in response.json()] == [20010, 0]
    job = queue_client.get(f"/api/jobs/{response.headers['X-Dncq-Job']}").json()
    attempts = {t["machineID"]: (t["attempts"], t["statusMsg"]) for t in job["targets"]}
    assert attempts["locked"][0] == 1  # the machine refuses it again: not retried
    assert "9000-9999" in attempts["locked"][1]
    listed = queue_client.get("/api/cnc/readProgramList", params={"machineID": "free"}).json()
    assert listed["programs"] == ["9001"]


def test_one_machine_never_runs_more_operations_than_its_limit(
        queue_client, add_machines, queue_settings, caplog):
    add_machines({"id": "solo", "name": "Solo", "model": "Mock",
                  "options": {"latency_ms": 30}})
    jobs = []
    for j in range(3):  # three jobs at once, each with several targets on the one machine
        jobs.append(queue_client.post("/api/jobs", json={
            "kind": "send", "content": PROGRAM,
            "targets": [{"machineID": "solo", "fileName": f"J{j}_{i}.nc"} for i in range(4)],
        }).json()["id"])
    for job_id in jobs:
        wait_done(queue_client, job_id)
    # A lease the host was too slow to renew (3 s in these tests) is logged: say so if it was.
    assert mock_of(queue_settings, "solo").peak_active() == 1, \
        [r.getMessage() for r in caplog.records if r.name == "jobs.run.leases"]
    assert len(list((queue_settings.data_dir / "mock" / "solo" / "files").iterdir())) == 12


def test_targets_of_one_machine_run_in_request_order(queue_client, add_machines):
    add_machines({"id": "solo", "name": "Solo", "model": "Mock",
                  "options": {"latency_ms": 10}})
    names = [f"N{i}.nc" for i in range(6)]
    response = queue_client.post("/api/cnc/batchSendFile", json={
        "content": PROGRAM, "targets": [{"machineID": "solo", "fileName": n} for n in names]})
    job = queue_client.get(f"/api/jobs/{response.headers['X-Dncq-Job']}").json()
    started = [t["startedAt"] for t in job["targets"]]
    assert started == sorted(started)


def test_a_machine_that_comes_back_online_gets_its_file_on_a_later_attempt(
        queue_client, add_machines, queue_settings):
    add_machines({"id": "flaky", "name": "Flaky", "model": "Mock", "options": {}})
    mock = mock_of(queue_settings, "flaky")
    mock.set_options(offline=True)
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "max_attempts": 50,
        "targets": [{"machineID": "flaky", "fileName": "P.nc"}]}).json()["id"]
    wait_until(lambda: len(queue_client.get(f"/api/jobs/{job_id}").json()
                           ["targets"][0]["history"]) >= 2)  # two attempts failed
    mock.set_options(offline=False)
    job = wait_done(queue_client, job_id)
    target = job["targets"][0]
    assert target["errorCode"] == 0
    assert target["attempts"] >= 3
    assert [a["errorCode"] for a in target["history"]][:2] == [20004, 20004]


def test_permanent_errors_are_not_retried(queue_client, add_machines, queue_settings):
    add_machines(*mocks(1))
    job_id = queue_client.post("/api/jobs", json={
        "kind": "delete", "targets": [{"machineID": "m000", "fileName": "missing.nc"}],
    }).json()["id"]
    job = wait_done(queue_client, job_id)
    assert job["targets"][0]["errorCode"] == 158
    assert job["targets"][0]["attempts"] == 1


def test_a_permanent_failure_of_the_machine_s_transport_fails_at_once_in_its_words(
        queue_client, add_machines, queue_settings):
    # A mock machine's options.json that is not JSON fails every attempt alike: trying
    # again waited out max_attempts with backoff for an answer that cannot change.
    add_machines(*mocks(1))
    options = queue_settings.data_dir / "mock" / "m000" / "options.json"
    options.parent.mkdir(parents=True, exist_ok=True)
    options.write_text("{offline: true")
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "max_attempts": 5,
        "targets": [{"machineID": "m000", "fileName": "P.nc"}]}).json()["id"]
    target = wait_done(queue_client, job_id)["targets"][0]
    assert (target["errorCode"], target["attempts"]) == (20006, 1)
    assert target["statusMsg"].startswith("options.json of this mock machine is not JSON")


def test_a_machine_offline_for_the_whole_retry_window_ends_failed(
        queue_client, add_machines):
    add_machines({"id": "off", "name": "Off", "model": "Mock", "options": {"offline": True}})
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "deliver_within": "2s",
        "targets": [{"machineID": "off", "fileName": "P.nc"}]}).json()["id"]
    job = wait_done(queue_client, job_id, timeout_s=30)
    assert job["state"] == "failed"
    assert job["targets"][0]["errorCode"] == 20004
    assert job["targets"][0]["attempts"] >= 2


@pytest.mark.parametrize("window", ["forever", "-8h", "nan", -5, 0, 1e308, "99999999999h"])
def test_a_bad_delivery_window_is_refused_and_nothing_is_queued(queue_client, add_machines,
                                                                 window):
    add_machines(*mocks(1))
    response = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "deliver_within": window,
        "targets": [{"machineID": "m000", "fileName": "P.nc"}]})
    assert response.status_code == 400
    assert response.json()["errorCode"] == 20001
    assert "deliver_within" in response.json()["statusMsg"]
    assert queue_client.get("/api/jobs").json() == []


@pytest.mark.parametrize(("change", "code"), [("disable", 20011), ("remove", 10003)])
def test_a_machine_disabled_or_removed_mid_job_takes_no_more_of_its_targets(
        queue_client, add_machines, queue_settings, change, code):
    # Slow enough that the change lands while the first target runs, on a loaded host too.
    add_machines({"id": "slow", "name": "Slow", "model": "Mock", "options": {"latency_ms": 1500}})
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": "slow", "fileName": f"P{i}.nc"} for i in range(3)]}).json()["id"]
    # The change lands while the first target runs (not a later one, on a slow host).
    wait_until(lambda: queue_client.get(f"/api/jobs/{job_id}").json()["targets"][0]["state"]
               == "running")

    if change == "disable":
        changed = queue_client.put("/api/machines/slow", json={
            "id": "slow", "name": "Slow", "model": "Mock", "enabled": False,
            "options": {"latency_ms": 1500}})
        assert changed.status_code == 200, changed.json()
    else:
        queue_client.delete("/api/machines/slow")
    changed_at = datetime.now(UTC)
    job = wait_done(queue_client, job_id)

    codes = [t["errorCode"] for t in job["targets"]]
    assert codes[0] == 0 and codes[-1] == code
    # A target its runner took before the change was committed may still run (on a loaded
    # host the change can land after the first target); none taken after it does.
    for target in job["targets"]:
        if target["startedAt"] is None or \
                datetime.fromisoformat(target["startedAt"]) > changed_at:
            assert target["errorCode"] == code, target
    files = queue_settings.data_dir / "mock" / "slow" / "files"
    assert sorted(p.name for p in files.iterdir()) == \
        [f"P{i}.nc" for i, c in enumerate(codes) if c == 0]


def test_max_attempts_still_counts_within_a_delivery_window(queue_client, add_machines):
    add_machines({"id": "off", "name": "Off", "model": "Mock", "options": {"offline": True}})
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "deliver_within": "1h", "max_attempts": 2,
        "targets": [{"machineID": "off", "fileName": "P.nc"}]}).json()["id"]
    job = wait_done(queue_client, job_id, timeout_s=30)
    assert (job["targets"][0]["errorCode"], job["targets"][0]["attempts"]) == (20004, 2)


def test_targets_and_a_machine_selection_together_are_refused(queue_client, add_machines):
    add_machines(*mocks(2))
    response = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "machines": {"ids": ["m001"]},
        "targets": [{"machineID": "m000", "fileName": "P.nc"}]})
    assert response.status_code == 422 and "not both" in response.json()["statusMsg"]
    assert queue_client.get("/api/jobs").json() == []


def test_a_target_refused_when_the_job_was_made_is_not_retried(queue_client, add_machines):
    add_machines(*mocks(1))
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": "m000", "fileName": "P.nc"}, {"fileName": "Q.nc"}]}).json()["id"]
    job = wait_done(queue_client, job_id)
    before = job["targets"][1]
    assert before["errorCode"] == 20001

    assert queue_client.post(f"/api/jobs/{job_id}/retry").json()["retried"] == 0
    after = queue_client.get(f"/api/jobs/{job_id}").json()["targets"][1]
    assert (after["errorCode"], after["statusMsg"]) == (20001, before["statusMsg"])


def test_retry_runs_only_the_failed_targets(queue_client, add_machines, queue_settings):
    add_machines(*mocks(2))
    blocker = queue_settings.data_dir / "mock" / "m001" / "files" / "P.nc"
    blocker.parent.mkdir(parents=True, exist_ok=True)
    blocker.write_text("old")
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": "m000", "fileName": "P.nc"},
                    {"machineID": "m001", "fileName": "P.nc"}]}).json()["id"]
    wait_done(queue_client, job_id)
    blocker.unlink()
    assert queue_client.post(f"/api/jobs/{job_id}/retry").json()["retried"] == 1
    job = wait_done(queue_client, job_id)
    assert [t["errorCode"] for t in job["targets"]] == [0, 0]
    assert [t["attempts"] for t in job["targets"]] == [1, 2]
    assert [a["errorCode"] for a in job["targets"][1]["history"]] == [142, 0]


def test_cancel_stops_targets_not_started_and_lets_the_running_one_finish(
        queue_client, add_machines, queue_settings):
    add_machines({"id": "slow", "name": "Slow", "model": "Mock",
                  "options": {"latency_ms": 400}})
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": "slow", "fileName": f"P{i}.nc"} for i in range(6)],
    }).json()["id"]
    wait_until(lambda: any(t.state is TargetState.RUNNING
                           for t in target_rows(queue_settings, job_id)))
    cancelled = queue_client.post(f"/api/jobs/{job_id}/cancel").json()["cancelled"]
    job = wait_done(queue_client, job_id)
    states = [t["state"] for t in job["targets"]]
    assert cancelled >= 1
    assert states.count("cancelled") == cancelled
    assert "running" not in states and "pending" not in states
    assert job["state"] == "cancelled"


def test_a_running_target_that_fails_after_its_job_was_cancelled_is_cancelled_not_retried(
        queue_client, add_machines, queue_settings):
    # The listing's 3 s are the window for the cancel: under load, 0.8 s was sometimes
    # gone before the cancel came, and the read had already failed and gone back to pending.
    add_machines({"id": "slow", "name": "Slow", "model": "Mock",
                  "options": {"latency_ms": 3000}})
    mock_file(queue_settings, "slow", "P.nc", PROGRAM)
    job_id = queue_client.post("/api/jobs", json={  # a listing, then a read: two steps
        "kind": "backup", "machines": {"ids": ["slow"]}}).json()["id"]
    slow = mock_of(queue_settings, "slow")
    # The listing itself has begun, not only the target: taken offline between the two,
    # the machine failed the listing, and under load that failure was back to pending
    # before the cancel came.
    wait_until(lambda: slow.peak_active() == 1)
    assert target_rows(queue_settings, job_id)[0].state is TargetState.RUNNING

    slow.set_options(offline=True)  # its next step fails, transient
    assert queue_client.post(f"/api/jobs/{job_id}/cancel").json()["cancelled"] == 0

    job = wait_done(queue_client, job_id, timeout_s=30)
    target = job["targets"][0]
    assert (job["state"], target["state"], target["errorCode"]) == ("cancelled", "cancelled", 20015)
    assert target["attempts"] == 1  # no retry after the cancel


def test_a_cancelled_target_whose_worker_died_mid_attempt_says_that_attempt_may_have_got_through(
        client, add_machines, settings):
    # Cancelled rather than run again: the attempt cut off may have sent the file already,
    # which "cancelled on request" alone denied.
    add_machines(*mocks(2))
    job_id = client.post("/api/jobs", json={  # queued; no worker
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": "m000", "fileName": "P.nc"},
                    {"machineID": "m001", "fileName": "P.nc"}]}).json()["id"]
    with db.session_scope(settings.resolved_database_url) as session:  # as the reaper leaves it
        session.execute(update(Target).where(Target.job_id == job_id,
                                             Target.machine_id == "m001")
                        .values(interrupted=True, attempts=1))
    client.post(f"/api/jobs/{job_id}/cancel")

    said = [t["statusMsg"] for t in client.get(f"/api/jobs/{job_id}").json()["targets"]]
    assert said == ["cancelled on request", "cancelled on request; an attempt cut off (its "
                    "worker lost, or its connection) may have got through"]


def test_a_target_put_back_by_the_reaper_after_its_job_was_cancelled_ends_cancelled(
        request, queue_settings, add_machines):
    from fastapi.testclient import TestClient

    from jobs.api.app import create_app
    from tests.conftest import API_KEY

    add_machines(*mocks(1))
    with TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as client:
        job_id = client.post("/api/jobs", json={  # queued; no worker yet
            "kind": "send", "content": PROGRAM,
            "targets": [{"machineID": "m000", "fileName": "P.nc"}]}).json()["id"]
        client.post(f"/api/jobs/{job_id}/cancel")
        # What the reaper does to a target whose worker died mid-attempt: due, unqueued.
        with db.session_scope(queue_settings.resolved_database_url) as session:
            session.execute(update(Target).where(Target.job_id == job_id).values(
                state=TargetState.PENDING, finished_at=None, interrupted=True,
                dispatched_at=None))
        request.getfixturevalue("celery_worker")  # the job's task, then the reaper's

        job = wait_done(client, job_id, timeout_s=30)

    assert (job["state"], job["targets"][0]["state"]) == ("cancelled", "cancelled")
    assert not (queue_settings.data_dir / "mock" / "m000" / "files" / "P.nc").exists()


def machine_with_old_program(add_machines: Any, settings: Any) -> Any:
    """One mock machine, m000, whose P.nc holds "old program"; the path of that file."""
    add_machines(*mocks(1))
    path = settings.data_dir / "mock" / "m000" / "files" / "P.nc"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("old program\n")
    return path


def restore_replaced(client: Any, job_id: str) -> None:
    """Put back every file the job replaced, and wait until that is done."""
    wait_done(client, client.post(f"/api/jobs/{job_id}/restore-replaced").json()["id"])


def test_replace_keeps_the_old_file_and_restore_puts_it_back(
        queue_client, add_machines, queue_settings):
    path = machine_with_old_program(add_machines, queue_settings)
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "replace": True,
        "targets": [{"machineID": "m000", "fileName": "P.nc"}]}).json()["id"]
    job = wait_done(queue_client, job_id)
    assert job["targets"][0]["errorCode"] == 0 and job["targets"][0]["replacedCopy"]
    assert path.read_text() == PROGRAM
    restore_replaced(queue_client, job_id)
    assert path.read_text() == "old program\n"


@pytest.mark.parametrize(("failure", "code"), [
    (Dropped("link lost"), 20006),
    # A worker killed between the delete and the record of the result, or an unexpected
    # error there, loses what the attempt returns: the copy is the target's before the delete.
    (RuntimeError("the worker's process is gone"), 20017),
])
def test_replace_keeps_the_old_copy_when_the_new_write_fails_after_the_delete(
        queue_client, add_machines, queue_settings, monkeypatch, failure: Exception,
        code: int):
    from worker.transports.mock import MockTransport

    path = machine_with_old_program(add_machines, queue_settings)
    write, calls = MockTransport.write, []

    def fails_once(self: MockTransport, *args: Any, **kwargs: Any) -> int:
        calls.append(args[0])
        if len(calls) == 2:  # the write after the old file was deleted
            raise failure
        return write(self, *args, **kwargs)

    monkeypatch.setattr(MockTransport, "write", fails_once)
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "replace": True, "max_attempts": 1,
        "targets": [{"machineID": "m000", "fileName": "P.nc"}]}).json()["id"]
    job = wait_done(queue_client, job_id)
    assert job["targets"][0]["errorCode"] == code and job["targets"][0]["replacedCopy"]
    assert not path.exists()  # the machine lost its program ...

    restore_replaced(queue_client, job_id)
    assert path.read_text() == "old program\n"  # ... and gets it back


def test_a_target_named_twice_in_a_replace_job_keeps_the_first_old_copy(
        queue_client, add_machines, queue_settings):
    path = machine_with_old_program(add_machines, queue_settings)
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "replace": True,
        "targets": [{"machineID": "m000", "fileName": "P.nc"}] * 2}).json()["id"]
    job = wait_done(queue_client, job_id)
    assert [t["errorCode"] for t in job["targets"]] == [0, 0]
    assert [t["replacedCopy"] for t in job["targets"]] == [True, False]

    restore_replaced(queue_client, job_id)
    assert path.read_text() == "old program\n"


def test_replace_refuses_the_running_program_unless_forced(queue_client, add_machines,
                                                           queue_settings):
    add_machines({"id": "run", "name": "Run", "model": "Mock",
                  "options": {"current_program": "P.nc"}})
    path = queue_settings.data_dir / "mock" / "run" / "files" / "P.nc"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("running\n")
    request = {"kind": "send", "content": PROGRAM, "replace": True,
               "targets": [{"machineID": "run", "fileName": "P.nc"}]}
    job = wait_done(queue_client, queue_client.post("/api/jobs", json=request).json()["id"])
    assert job["targets"][0]["errorCode"] == 20008
    assert path.read_text() == "running\n"
    forced = queue_client.post("/api/jobs", json={**request, "force": True}).json()
    assert wait_done(queue_client, forced["id"])["targets"][0]["errorCode"] == 0
    assert path.read_text() == PROGRAM


def test_batch_delete_of_the_running_program_needs_force_true_in_the_query(
        queue_client, add_machines, queue_settings):
    add_machines({"id": "run", "name": "Run", "model": "Mock",
                  "options": {"current_program": "P.nc"}})
    path = queue_settings.data_dir / "mock" / "run" / "files" / "P.nc"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("running\n")
    targets = [{"machineID": "run", "fileName": "P.nc"}]

    refused = queue_client.post("/api/cnc/batchDeleteFile", json=targets).json()
    assert refused[0]["errorCode"] == 20008 and path.exists()
    forced = queue_client.post("/api/cnc/batchDeleteFile", params={"force": "true"},
                               json=targets).json()
    assert forced == [{"errorCode": 0, "errorMsg": "Success"}]
    assert not path.exists()


def test_skip_identical_makes_a_rollout_safe_to_run_again(queue_client, add_machines):
    add_machines(*mocks(2))
    request = {"kind": "send", "content": PROGRAM, "skip_identical": True,
               "targets": [{"machineID": "m000", "fileName": "P.nc"},
                           {"machineID": "m001", "fileName": "P.nc"}]}
    first = wait_done(queue_client, queue_client.post("/api/jobs", json=request).json()["id"])
    again = wait_done(queue_client, queue_client.post("/api/jobs", json=request).json()["id"])
    assert [t["state"] for t in first["targets"]] == ["succeeded", "succeeded"]
    assert [t["state"] for t in again["targets"]] == ["skipped", "skipped"]
    assert again["state"] == "succeeded"


def test_abort_after_failures_cancels_the_rest(queue_client, add_machines):
    add_machines({"id": "solo", "name": "Solo", "model": "Mock", "options": {}})
    targets = [{"machineID": "solo", "fileName": "bad/name"} for _ in range(2)]
    targets += [{"machineID": "solo", "fileName": f"P{i}.nc"} for i in range(3)]
    job = wait_done(queue_client, queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "abort_after_failures": 2,
        "targets": targets}).json()["id"])
    assert [t["state"] for t in job["targets"]] == ["failed"] * 2 + ["cancelled"] * 3


def test_dry_run_lists_what_would_happen_and_changes_nothing(
        queue_client, add_machines, queue_settings):
    add_machines(*mocks(3))
    existing = queue_settings.data_dir / "mock" / "m001" / "files" / "P.nc"
    existing.parent.mkdir(parents=True, exist_ok=True)
    existing.write_text("old")
    same = queue_settings.data_dir / "mock" / "m002" / "files" / "P.nc"
    same.parent.mkdir(parents=True, exist_ok=True)
    same.write_text(PROGRAM)
    plan = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "dry_run": True, "replace": True,
        "machines": {"all": True}, "fileName": "P.nc"}).json()
    assert [t["action"] for t in plan["targets"]] == [
        "send as P.nc", "replace (old file kept)", "nothing to replace (the same file is there)"]
    assert existing.read_text() == "old"
    assert not (queue_settings.data_dir / "mock" / "m000" / "files" / "P.nc").exists()
    assert queue_client.get("/api/jobs").json() == []


def test_two_dry_runs_at_once_ask_each_machine_one_operation_at_a_time(
        add_machines, queue_settings):
    add_machines(*mocks(2, latency_ms=100))
    with serving(create_app(queue_settings)) as live, httpx.Client(
            base_url=live.url, timeout=HTTP_TIMEOUT_S) as http:

        def dry_run() -> dict[str, Any]:
            return http.post("/api/jobs", headers={"X-Api-Key": API_KEY}, json={
                "kind": "delete", "dry_run": True, "force": True, "machines": {"all": True},
                "fileName": "P.nc"}).json()

        plans = at_once(dry_run, dry_run)

    assert [[t["errorCode"] for t in plan["targets"]] for plan in plans] == [[158, 158]] * 2
    assert [mock_of(queue_settings, m).peak_active() for m in ("m000", "m001")] == [1, 1]


def test_a_single_request_waits_for_a_busy_machine_then_answers_busy(
        queue_client, add_machines):
    add_machines({"id": "slow", "name": "Slow", "model": "Mock",
                  "options": {"latency_ms": 1500}})
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": "slow", "fileName": f"P{i}.nc"} for i in range(3)],
    }).json()["id"]
    wait_until(lambda: queue_client.get(f"/api/jobs/{job_id}").json()["counts"]["running"])
    body = queue_client.get("/api/cnc/readProgramList", params={"machineID": "slow"}).json()
    assert body["errorCode"] == 20007


# -- helpers ---------------------------------------------------------------------------


def target_rows(settings: Any, job_id: str) -> list[Target]:
    from sqlalchemy import select

    with db.session_scope(settings.resolved_database_url) as session:
        return list(session.scalars(select(Target).where(Target.job_id == job_id)
                                    .order_by(Target.position)))


def test_results_stay_in_request_order_with_random_latency_and_faults(
        queue_client, add_machines, queue_settings):
    import random

    rng = random.Random(7)
    add_machines(*[{"id": f"r{i}", "name": f"R{i}", "model": "Mock",
                    "options": {"latency_ms": rng.randint(0, 80), "fail_rate": 0.3, "seed": i}}
                   for i in range(8)])
    targets, expected = [], []
    for n in range(40):
        kind = rng.choice(["ok", "ok", "exists", "unknown"])
        machine = "nope" if kind == "unknown" else f"r{rng.randrange(8)}"
        name = f"T{n}.nc"
        if kind == "exists":
            path = queue_settings.data_dir / "mock" / machine / "files" / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("old")
        targets.append({"machineID": machine, "fileName": name})
        expected.append({"ok": 0, "exists": 142, "unknown": 10003}[kind])
    response = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM, "max_attempts": 30, "targets": targets})
    job = wait_done(queue_client, response.json()["id"], timeout_s=120)
    assert [t["errorCode"] for t in job["targets"]] == expected
    assert any(t["attempts"] > 1 for t in job["targets"])  # the faults did happen
    with db.session_scope(queue_settings.resolved_database_url) as session:
        results = json.loads(job_views.results_json(session=session, job_id=job["id"]))
    assert [r["errorCode"] for r in results] == expected


def test_health_reports_database_broker_and_workers(queue_client):
    body = queue_client.get("/api/health").json()
    assert body["database"] == "ok" and body["broker"] == "ok"
    assert body["workers"] >= 1


def test_batch_and_backup_targets_read_both_spellings_alike() -> None:
    from jobs.backup.streamed import BackupTarget
    from jobs.service import TargetIn

    raw = {"MachineID": 1010, "dirAtCNC": "//CNC_MEM/B", "DirAtCNC": "//CNC_MEM/A",
           "SubDir": "sub", "FileName": "O1"}
    batch, backup = TargetIn.parse(raw), BackupTarget.parse(raw, 0)
    for target in (batch, backup):
        assert (target.machineID, target.dirAtCNC, target.subDir, target.fileName) == \
            ("1010", "//CNC_MEM/B", "sub", "O1")


def test_text_sent_without_an_encoding_is_written_in_each_machine_s_own_or_fails_where_it_cannot_be(
        queue_client, add_machines, queue_settings):
    add_machines({"id": "eu", "name": "EU", "model": "Mock", "encoding": "latin-1"},
                 {"id": "uni", "name": "Uni", "model": "Mock"},
                 {"id": "old", "name": "Old", "model": "Mock", "encoding": "ascii"})
    text = "(Größe 3)\nG0 X0\nM30\n"

    body = queue_client.post("/api/cnc/batchSendFile", json={"content": text, "targets": [
        {"machineID": m, "fileName": "G.nc"} for m in ("eu", "uni", "old")]}).json()

    assert [r["errorCode"] for r in body] == [0, 0, 20001]
    assert on_machine(queue_settings, "eu", "G.nc").read_bytes() == text.encode("latin-1")
    assert on_machine(queue_settings, "uni", "G.nc").read_bytes() == text.encode("utf-8")
    assert not on_machine(queue_settings, "old", "G.nc").exists()


@pytest.mark.parametrize("file", [{"base64": "@@"}, {"content": "x", "encoding": "nope"},
                                  {"content": "é", "encoding": "us-ascii"}])
def test_a_file_that_cannot_be_read_fails_every_target_in_place_as_an_array(
        queue_client, add_machines, queue_settings, file):
    add_machines(*mocks(2))
    response = queue_client.post("/api/cnc/batchSendFile", json={**file, "targets": [
        {"machineID": "m000", "fileName": "P.nc"}, {"machineID": "nope", "fileName": "P.nc"},
        {"machineID": "m001", "fileName": "P.nc"}]})

    assert response.status_code == 200
    assert [r["errorCode"] for r in response.json()] == [20001, 10003, 20001]
    assert not on_machine(queue_settings, "m000", "P.nc").exists()
    job = queue_client.get(f"/api/jobs/{response.headers['X-Dncq-Job']}").json()
    assert job["state"] == "failed"


def test_a_batch_send_without_any_file_cannot_be_parsed(queue_client, add_machines):
    add_machines(*mocks(1))
    response = queue_client.post("/api/cnc/batchSendFile", json={
        "targets": [{"machineID": "m000", "fileName": "P.nc"}]})

    assert response.status_code == 400 and response.json()["errorCode"] == 20001
    assert queue_client.get("/api/jobs").json() == []


def test_a_target_that_is_no_object_fails_at_its_own_position(
        queue_client, add_machines, queue_settings):
    add_machines(*mocks(1))
    sent = queue_client.post("/api/cnc/batchSendFile", json={"content": PROGRAM, "targets": [
        "m000", {"machineID": "m000", "fileName": "P.nc"}]})
    on_machine(queue_settings, "m000", "Q.nc").write_text(PROGRAM)
    deleted = queue_client.post("/api/cnc/batchDeleteFile", json=[
        {"machineID": "m000", "fileName": "Q.nc"}, 7])

    assert [r["errorCode"] for r in sent.json()] == [20001, 0]
    assert [r["errorCode"] for r in deleted.json()] == [0, 20001]
    assert not on_machine(queue_settings, "m000", "Q.nc").exists()
