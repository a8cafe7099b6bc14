"""A job's end said on Redis wakes the batch request waiting for it; without Redis, or
when Redis is gone, the request still finds the end by looking."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from jobs.api import waiting
from jobs.run import job_ends
from jobs.settings import Settings
from tests.servers import RedisServer, free_port

PROGRAM = "G21 G90\nG0 X0 Y0\nM30\n"


async def _wait_once(settings: Settings, job_id: str, timeout_s: float,
                     said: str | None = None, say_after_s: float = 0.2) -> tuple[bool, float]:
    """Listen for `job_id`, have `said` announced from a thread, and wait once."""
    async with job_ends.listening(settings, job_id) as listener:
        if said is not None:
            threading.Timer(say_after_s, job_ends.announce, (settings, said)).start()
        started = time.monotonic()
        told = await listener.wait(timeout_s)
        return told, time.monotonic() - started


def test_an_end_said_on_redis_ends_the_wait(queue_settings: Settings) -> None:
    told, waited_s = asyncio.run(_wait_once(queue_settings, "j1", 30.0, said="j1"))
    assert told
    assert waited_s < 15  # woken by the message, not by the end of the 30 s wait


def test_the_end_of_another_job_does_not_end_the_wait(queue_settings: Settings) -> None:
    told, waited_s = asyncio.run(_wait_once(queue_settings, "j1", 0.5, said="j2",
                                            say_after_s=0.05))
    assert not told
    assert waited_s >= 0.5


def test_without_redis_the_wait_sleeps_and_saying_is_a_no_op(settings: Settings) -> None:
    assert settings.broker_url is None  # the embedded queue
    job_ends.announce(settings, "j1")
    told, waited_s = asyncio.run(_wait_once(settings, "j1", 0.2))
    assert not told
    assert waited_s >= 0.2


def test_a_redis_that_cannot_be_reached_leaves_the_wait_to_sleep(settings: Settings) -> None:
    nowhere = settings.model_copy(update={"broker_url": f"redis://127.0.0.1:{free_port()}/0"})
    job_ends.announce(nowhere, "j1")  # says nothing, raises nothing
    told, waited_s = asyncio.run(_wait_once(nowhere, "j1", 0.2))
    assert not told
    assert waited_s >= 0.2


def test_a_redis_that_goes_away_while_listened_to_leaves_the_wait_to_sleep(
        settings: Settings, tmp_path: Path) -> None:
    server = RedisServer(tmp_path)
    server.start()
    own = settings.model_copy(update={"broker_url": server.url})

    async def scenario() -> list[tuple[bool, float]]:
        async with job_ends.listening(own, "j1") as listener:
            assert listener.live
            server.kill()
            waits = []
            for _ in range(2):  # the first notices the loss, the second only sleeps
                started = time.monotonic()
                told = await listener.wait(0.3)
                waits.append((told, time.monotonic() - started))
            assert not listener.live
            return waits

    try:
        waits = asyncio.run(scenario())
    finally:
        server.kill()
    assert [told for told, _ in waits] == [False, False]
    assert all(waited_s >= 0.3 for _, waited_s in waits)


def test_a_batch_request_answers_when_the_worker_says_its_job_ended(
        queue_client: Any, add_machines: Any, queue_settings: Settings,
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Pauses of a minute between looks: only the worker's message can end the wait sooner.
    monkeypatch.setattr(waiting, "POLL_MIN_S", 60.0)
    monkeypatch.setattr(waiting, "POLL_MAX_S", 60.0)
    add_machines(*[{"id": f"e{i}", "name": f"E{i}", "model": "Mock",
                    "options": {"latency_ms": 300}} for i in range(3)])
    started = time.monotonic()
    response = queue_client.post("/api/cnc/batchSendFile", json={
        "content": PROGRAM,
        "targets": [{"machineID": f"e{i}", "fileName": "P.nc"} for i in range(3)]})
    answered_s = time.monotonic() - started
    assert response.status_code == 200
    assert [r["errorCode"] for r in response.json()] == [0, 0, 0]  # final, not "running"
    assert answered_s < 30


@pytest.fixture
def slow_looks(monkeypatch: pytest.MonkeyPatch) -> None:
    """Pauses of a minute between looks: only a message can end a wait sooner."""
    monkeypatch.setattr(waiting, "POLL_MIN_S", 60.0)
    monkeypatch.setattr(waiting, "POLL_MAX_S", 60.0)


def test_a_job_asked_with_wait_s_is_answered_when_it_ends(
        queue_client: Any, add_machines: Any, slow_looks: None) -> None:
    add_machines(*[{"id": f"w{i}", "name": f"W{i}", "model": "Mock",
                    "options": {"latency_ms": 300}} for i in range(2)])
    job = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": f"w{i}", "fileName": "P.nc"} for i in range(2)]}).json()
    started = time.monotonic()
    view = queue_client.get(f"/api/jobs/{job['id']}", params={"wait_s": 50}).json()
    assert view["counts"]["succeeded"] == 2
    assert time.monotonic() - started < 30  # the end was said, not found at a look


def test_a_wait_for_a_job_ends_after_wait_s_with_the_job_still_running(
        queue_client: Any, add_machines: Any) -> None:
    add_machines({"id": "slow", "name": "Slow", "model": "Mock",
                  "options": {"latency_ms": 3000}})
    job = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": "slow", "fileName": "P.nc"}]}).json()
    started = time.monotonic()
    view = queue_client.get(f"/api/jobs/{job['id']}", params={"wait_s": 0.3}).json()
    assert time.monotonic() - started >= 0.3  # it did wait
    assert view["counts"]["pending"] + view["counts"]["running"] == 1


def test_waits_that_are_too_long_or_for_no_job_are_refused_or_answered_at_once(
        queue_client: Any) -> None:
    started = time.monotonic()
    assert queue_client.get("/api/jobs/nope", params={"wait_s": 50}).status_code == 404
    assert queue_client.get("/api/backups", params={"job": "nope", "wait_s": 50}).json() == []
    assert time.monotonic() - started < 30  # nothing to wait for: no such job
    assert queue_client.get("/api/jobs/nope",
                            params={"wait_s": waiting.WAIT_MAX_S + 1}).status_code == 400
    refused = queue_client.get("/api/backups", params={"wait_s": 1})
    assert refused.status_code == 400
    assert "job" in refused.json()["statusMsg"]


def test_a_backup_asked_for_with_wait_s_is_answered_once_its_zip_is_registered(
        queue_client: Any, add_machines: Any, queue_settings: Settings,
        slow_looks: None) -> None:
    add_machines(*[{"id": f"k{i}", "name": f"K{i}", "model": "Mock",
                    "options": {"latency_ms": 100}} for i in range(2)])
    for i in range(2):
        program = queue_settings.data_dir / "mock" / f"k{i}" / "files" / "O1000.nc"
        program.parent.mkdir(parents=True, exist_ok=True)
        program.write_text(PROGRAM)
    job = queue_client.post("/api/jobs", json={"kind": "backup",
                                               "machines": {"all": True}}).json()
    started = time.monotonic()
    found = queue_client.get("/api/backups", params={"job": job["id"], "wait_s": 50}).json()
    assert [b["job"] for b in found] == [job["id"]]
    assert found[0]["files"] == 2
    assert time.monotonic() - started < 30


def _looks_in_half_a_second(settings: Settings, job_id: str) -> int:
    counted = [0]

    def reached(*, session: Any, job_id: str) -> bool:
        counted[0] += 1
        return False

    assert not asyncio.run(waiting.until(settings, job_id, 0.5, reached))
    return counted[0]


def test_a_long_running_job_is_looked_at_ten_times_a_second_by_every_new_wait(
        settings: Settings, add_machines: Any) -> None:
    # A client asking every half second for an hour-long job starts a new wait each time:
    # the looks follow the job's age, not the wait's, or each ask would begin with quick ones.
    from datetime import timedelta

    from sqlalchemy import update

    from jobs import db, service
    from jobs.models import Job, JobKind, utcnow

    add_machines({"id": "m1", "name": "M1", "model": "Mock"})
    url = settings.resolved_database_url
    ages = {"fresh": timedelta(0), "old": timedelta(hours=1)}
    job_ids = {}
    for name, age in ages.items():
        with db.session_scope(url) as session:
            job = service.create(session=session, kind=JobKind.SEND, targets=[
                service.TargetIn.parse({"machineID": "m1", "fileName": "P.nc"})])
            session.execute(update(Job).where(Job.id == job.id)
                            .values(created_at=utcnow() - age))
            job_ids[name] = job.id

    looks = {name: _looks_in_half_a_second(settings, job_id)
             for name, job_id in job_ids.items()}
    assert looks["old"] <= 7  # 0.1 s apart
    assert looks["fresh"] > looks["old"]


def test_hearing_redis_a_wait_looks_only_ten_times_a_second_even_for_a_new_job(
        queue_settings: Settings, add_machines: Any) -> None:
    from jobs import db, service
    from jobs.models import JobKind

    add_machines({"id": "m1", "name": "M1", "model": "Mock"})
    with db.session_scope(queue_settings.resolved_database_url) as session:
        job_id = service.create(session=session, kind=JobKind.SEND, targets=[
            service.TargetIn.parse({"machineID": "m1", "fileName": "P.nc"})]).id

    assert _looks_in_half_a_second(queue_settings, job_id) <= 7  # the end will be said


def test_two_requests_waiting_for_one_job_both_hear_its_end(queue_settings: Settings) -> None:
    async def both() -> list[bool]:
        async with job_ends.listening(queue_settings, "j2") as first, \
                job_ends.listening(queue_settings, "j2") as second:
            threading.Timer(0.2, job_ends.announce, (queue_settings, "j2")).start()
            return list(await asyncio.gather(first.wait(30.0), second.wait(30.0)))

    assert asyncio.run(both()) == [True, True]


def test_an_end_said_after_redis_restarted_is_heard(settings: Settings, tmp_path: Path) -> None:
    # The runner's client was connected before the restart; its next announce reconnects.
    server = RedisServer(tmp_path)
    server.start()
    own = settings.model_copy(update={"broker_url": server.url})
    try:
        assert asyncio.run(_wait_once(own, "before", 30.0, said="before"))[0]
        server.kill()
        job_ends.announce(own, "lost")  # Redis is down: nothing said, nothing raised
        server.start()  # the same port
        told, waited_s = asyncio.run(_wait_once(own, "after", 30.0, said="after"))
    finally:
        server.kill()
    assert told
    assert waited_s < 15


def test_a_batch_request_answers_when_its_job_is_cancelled(
        queue_client: Any, add_machines: Any, queue_settings: Settings,
        slow_looks: None) -> None:
    # An offline machine: its target waits between failed attempts, pending, when the
    # cancel comes; the cancel, not a runner, ends the job, and says so.
    add_machines({"id": "gone", "name": "Gone", "model": "Mock",
                  "options": {"offline": True}})
    answer: dict[str, Any] = {}

    def batch_request() -> None:
        answer["response"] = queue_client.post("/api/cnc/batchSendFile", json={
            "content": PROGRAM, "targets": [{"machineID": "gone", "fileName": "P.nc"}]})

    waiter = threading.Thread(target=batch_request)
    waiter.start()
    job_id = _wait_for_a_job(queue_client)
    started = time.monotonic()
    assert queue_client.post(f"/api/jobs/{job_id}/cancel").status_code == 200
    waiter.join(50)
    assert not waiter.is_alive()
    assert time.monotonic() - started < 30  # the cancel said so; no look for a minute
    assert [r["errorCode"] for r in answer["response"].json()] == [20015]


def _wait_for_a_job(client: Any) -> str:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        jobs = client.get("/api/jobs").json()
        if jobs and jobs[0]["counts"]["pending"] + jobs[0]["counts"]["running"]:
            return str(jobs[0]["id"])
        time.sleep(0.05)
    raise AssertionError("no job appeared")
