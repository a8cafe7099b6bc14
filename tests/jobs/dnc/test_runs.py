"""Drip-feed runs as jobs: started through the API, recorded per run, never run twice."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import httpx
import pytest
from sqlalchemy import select, text, update

from jobs import db
from jobs.api.app import create_app
from jobs.dnc import feeding, programs, runs
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import door, registry
from jobs.models import MachineLease, Run, RunState, Target, TargetState, utcnow
from jobs.run import reaper, targets
from jobs.run.work import Work
from tests.conftest import API_KEY
from tests.jobs.helpers import wait_done
from tests.live_server import serving
from tests.servers import PostgresServer, postgres_of_its_own
from worker import drip_run, runner
from worker.transports import dnc_wire as wire
from worker.transports.drip import DripResult, LinkLost

PROGRAM = b"O0010\nG0 X0 Y0\nG1 X10 F200\nM30\n"


def stored(client: Any, data: bytes = PROGRAM) -> dict[str, Any]:
    return client.post("/api/programs", content=data,
                       headers={"content-type": "application/octet-stream"}).json()


def start_run(client: Any, machine_id: str, program: dict[str, Any], **more: Any) -> Any:
    return client.post("/api/jobs", json={"kind": "dnc_run", "machines": {"ids": [machine_id]},
                                          "program": program["id"], "fileName": "PART.NC",
                                          **more})


def test_a_machine_whose_link_cannot_drip_feed_fails_the_run_and_says_why(
        queue_client, add_machines) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})  # the mock has no DNC link

    job = start_run(queue_client, "m1", stored(queue_client)).json()
    done = wait_done(queue_client, job["id"])

    assert done["kind"] == "dnc_run"
    assert done["targets"][0]["errorCode"] == 20003
    assert done["targets"][0]["attempts"] == 1
    [run] = done["runs"]
    assert run["state"] == "failed" and "drip-feed" in run["message"]
    assert queue_client.get("/api/runs", params={"machine": "m1"}).json()[0]["id"] == run["id"]


def test_a_run_on_an_unknown_machine_is_refused_before_anything_is_queued(
        queue_client, add_machines) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})

    answer = start_run(queue_client, "m9", stored(queue_client))

    assert answer.status_code == 422 and "m9" in answer.json()["statusMsg"]
    assert queue_client.get("/api/runs").json() == []


@pytest.mark.parametrize("file_name", ["../x", "a\u0000b", "BIG\u202ePART.NC", "A" * 70_000])
def test_a_run_under_a_name_that_is_no_plain_file_name_is_refused_before_anything_is_queued(
        client, add_machines, file_name: str) -> None:
    # The name the control is told: a path, a NUL or an invisible character ran to the
    # end, and 70,000 characters ended the worker's attempt on a traceback.
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})

    answer = start_run(client, "m1", stored(client), fileName=file_name)

    assert answer.status_code == 400 and answer.json()["errorCode"] == 20001
    assert client.get("/api/runs").json() == []


@pytest.mark.parametrize(("data", "said"), [
    (b"", "the program is empty"),
    (b"O0300\n(" + b"A" * 5000 + b")\nM30\n", "line 2 is 5,002 bytes long"),
])
def test_a_program_no_control_can_be_fed_is_refused_before_anything_is_queued(
        client, add_machines, data: bytes, said: str) -> None:
    # An empty one held a dnc control waiting for ever; a line over the link's frame was
    # found once the control had been told to expect the run, and the run retried.
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})

    answer = start_run(client, "m1", stored(client, data))

    assert answer.status_code == 422 and answer.json()["errorCode"] == 20001
    assert said in answer.json()["statusMsg"]
    assert client.get("/api/runs").json() == []


@pytest.mark.parametrize(("targets", "code"), [
    ([{"machineID": "m9"}], 10003), ([], 20001), ([{}], 10003)])
def test_run_targets_are_refused_whole_as_a_machine_selector_is(
        client, add_machines, targets: list[dict[str, str]], code: int) -> None:
    # Given as targets, an unknown machine queued a job that then failed, and none at all
    # answered 200: a selector of the same ids was refused with 422 before anything.
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})
    program = stored(client)

    answer = client.post("/api/jobs", json={"kind": "dnc_run", "targets": targets,
                                            "program": program["id"], "fileName": "PART.NC"})

    assert answer.status_code == 422 and answer.json()["errorCode"] == code, answer.text
    assert client.get("/api/runs").json() == [] and client.get("/api/jobs").json() == []


def test_run_targets_naming_a_machine_twice_make_one_run_in_a_dry_run_too(
        client, add_machines) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})

    plan = client.post("/api/jobs", json={
        "kind": "dnc_run", "targets": [{"machineID": "m1"}] * 2,
        "program": stored(client)["id"], "fileName": "PART.NC", "dry_run": True}).json()

    assert plan["machines"] == ["m1"]


def test_a_run_of_a_program_never_stored_is_not_found(client, add_machines) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})

    answer = start_run(client, "m1", {"id": "a" * 64})

    assert answer.status_code == 404 and answer.json()["errorCode"] == 158


def test_a_run_of_a_program_id_that_is_no_sha256_is_a_bad_request(client, add_machines) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})

    answer = start_run(client, "m1", {"id": "not-a-content-id"})

    assert answer.status_code == 400 and answer.json()["errorCode"] == 20001
    assert "SHA-256" in answer.json()["statusMsg"]


def test_a_finished_run_is_not_retried_from_the_top(queue_client, add_machines) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})
    job = start_run(queue_client, "m1", stored(queue_client)).json()
    wait_done(queue_client, job["id"])

    answer = queue_client.post(f"/api/jobs/{job['id']}/retry")

    assert answer.status_code == 409 and "--from-line" in answer.json()["statusMsg"]


def test_two_restart_points_at_once_are_refused(client, add_machines) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})

    answer = start_run(client, "m1", stored(client), from_line=2, from_block="N20")

    assert answer.status_code == 422 and "--from names the point alone" in \
        answer.json()["statusMsg"]


def test_a_run_on_a_machine_with_a_run_not_ended_is_refused_naming_it_unless_queued_behind(
        client, add_machines) -> None:
    # It was queued without a word: the stop of the first run, after a broken tool, started
    # the second one cutting the part from its first line.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    program = stored(client)
    first = start_run(client, "2001", program).json()

    refused = start_run(client, "2001", program)
    queued = start_run(client, "2001", program, queue=True)

    assert refused.status_code == 409 and refused.json()["errorCode"] == 20007
    said = refused.json()["statusMsg"]
    assert f"machine 2001 has a drip-feed run queued (job {first['id']}" in said
    assert f"dncq stop {first['id']}" in said and "--queue" in said
    assert said.endswith("it then starts when that one ends, however it ends")
    assert queued.status_code == 202
    assert [r["jobId"] for r in client.get("/api/runs").json()] == [queued.json()["id"],
                                                                    first["id"]]


def fed_run(client: Any, settings: Any, machine_id: str) -> dict[str, Any]:
    """A run's job on the machine, its target claimed and its run begun: being fed."""
    job = start_run(client, machine_id, stored(client)).json()
    targets.begin(settings=settings, job_id=job["id"], machine_id=machine_id)
    feeding.begin(url=settings.resolved_database_url, job_id=job["id"], machine_id=machine_id,
                  attempt=1, lease_ttl_s=settings.lease_ttl_s)
    return job


def claimed_again(settings: Any, job_id: str, machine_id: str) -> tuple[Work, Work]:
    """The job's target on the machine claimed, its runner stalled past its leases, queued
    again by the reaper and claimed by another: (the stale claim's work, the later's)."""
    stale = targets.begin(settings=settings, job_id=job_id, machine_id=machine_id)
    with db.session_scope(settings.resolved_database_url) as session:
        long_ago = utcnow() - timedelta(seconds=settings.lease_ttl_s * 4)
        session.execute(update(Target).where(Target.job_id == job_id)
                        .values(lease_until=long_ago))
        session.execute(update(MachineLease).where(MachineLease.holder == stale.holder)
                        .values(expires_at=long_ago))
    reaper.reap(settings=settings)
    later = targets.begin(settings=settings, job_id=job_id, machine_id=machine_id)
    assert stale.work is not None and later.work is not None
    return stale.work, later.work


def test_a_run_queued_behind_one_whose_link_reconnects_waits_while_that_ones_lease_lives(
        client, add_machines, settings) -> None:
    # A link that reconnects for its grace writes nothing to its run for longer than a lease
    # period, while its worker's heartbeat keeps its target's lease: it is still fed.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock", "max_concurrent": 2})
    url = settings.resolved_database_url
    first = fed_run(client, settings, "2001")
    with db.session_scope(url) as session:
        session.execute(update(Run).where(Run.job_id == first["id"]).values(
            updated_at=utcnow() - timedelta(seconds=settings.lease_ttl_s * 2)))
    behind = start_run(client, "2001", stored(client), queue=True).json()
    targets.begin(settings=settings, job_id=behind["id"], machine_id="2001")

    with pytest.raises(feeding.Behind):
        feeding.begin(url=url, job_id=behind["id"], machine_id="2001", attempt=1,
                      lease_ttl_s=settings.lease_ttl_s)

    with db.session_scope(url) as session:  # its worker lost too: the lease runs out
        session.execute(update(Target).where(Target.job_id == first["id"]).values(
            lease_until=utcnow() - timedelta(seconds=1)))
    targets.begin(settings=settings, job_id=behind["id"], machine_id="2001")
    assert feeding.begin(url=url, job_id=behind["id"], machine_id="2001", attempt=1,
                         lease_ttl_s=settings.lease_ttl_s).run_id


def test_a_job_whose_run_waits_behind_another_is_queued_not_running(
        client, add_machines, settings) -> None:
    # It said running while its run said queued: the operator took it for cutting.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock", "max_concurrent": 2})
    url = settings.resolved_database_url
    first = fed_run(client, settings, "2001")
    behind = start_run(client, "2001", stored(client), queue=True).json()
    targets.begin(settings=settings, job_id=behind["id"], machine_id="2001")
    with pytest.raises(feeding.Behind):
        feeding.begin(url=url, job_id=behind["id"], machine_id="2001", attempt=1,
                      lease_ttl_s=settings.lease_ttl_s)

    job = client.get(f"/api/jobs/{behind['id']}").json()

    assert (job["state"], job["runs"][0]["state"]) == ("queued", "queued")
    assert client.get(f"/api/jobs/{first['id']}").json()["state"] == "running"
    assert [j["id"] for j in client.get("/api/jobs", params={"state": "queued"}).json()] \
        == [behind["id"]]
    assert [j["id"] for j in client.get("/api/jobs", params={"state": "running"}).json()] \
        == [first["id"]]


def test_a_run_stopped_while_queued_behind_another_says_who_stopped_it_before_it_started(
        client, add_machines, settings) -> None:
    # Its target said "cancelled on request" while its job's stoppedBy named alice.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock", "max_concurrent": 2})
    first = fed_run(client, settings, "2001")
    behind = start_run(client, "2001", stored(client), queue=True).json()

    stopped = client.post(f"/api/jobs/{behind['id']}/stop", params={"by": "alice"})

    assert stopped.status_code == 200, stopped.text
    job = client.get(f"/api/jobs/{behind['id']}").json()
    [target], [run] = job["targets"], job["runs"]
    assert (job["state"], job["stoppedBy"]) == ("cancelled", "alice")
    assert target["state"] == "cancelled" and target["errorCode"] == 20015
    assert target["statusMsg"] == run["message"] == "stopped by alice before it started"
    assert run["state"] == "cancelled"
    assert client.get(f"/api/jobs/{first['id']}").json()["state"] == "running"


def test_a_run_stopped_after_its_runner_claimed_it_says_who_stopped_it_before_it_started(
        client, add_machines, settings) -> None:
    # A runner that claimed its target before the stop came finds it when it begins.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock", "max_concurrent": 2})
    url = settings.resolved_database_url
    fed_run(client, settings, "2001")
    behind = start_run(client, "2001", stored(client), queue=True).json()
    targets.begin(settings=settings, job_id=behind["id"], machine_id="2001")
    client.post(f"/api/jobs/{behind['id']}/stop", params={"by": "alice"})

    with pytest.raises(ContractError) as refused:
        feeding.begin(url=url, job_id=behind["id"], machine_id="2001", attempt=1,
                      lease_ttl_s=settings.lease_ttl_s)

    assert refused.value.code is ErrorCode.CANCELLED
    assert refused.value.status_msg == "stopped by alice before it started"


def test_a_run_behind_another_put_back_by_a_claim_gone_stale_keeps_the_later_claim(
        client, add_machines, settings) -> None:
    # Its runner stalled past its lease, the reaper queued the target again and another
    # runner claimed it: the stale runner, finding the machine fed, put that claim back.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock", "max_concurrent": 2})
    url = settings.resolved_database_url
    fed_run(client, settings, "2001")
    behind = start_run(client, "2001", stored(client), queue=True).json()
    stale, later = claimed_again(settings, behind["id"], "2001")

    with pytest.raises(feeding.Behind):
        feeding.begin(url=url, job_id=behind["id"], machine_id="2001",
                      attempt=stale.attempt, lease_ttl_s=settings.lease_ttl_s)

    [target] = client.get(f"/api/jobs/{behind['id']}").json()["targets"]
    assert (target["state"], target["attempts"]) == ("running", later.attempt)


def test_a_runner_whose_claim_went_stale_before_it_began_leaves_the_later_claims_run_running(
        client, add_machines, settings) -> None:
    # It took the later claim's run, running, for one whose worker stopped, and failed it
    # under the runner feeding it.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    url = settings.resolved_database_url
    job = start_run(client, "2001", stored(client)).json()
    stale, later = claimed_again(settings, job["id"], "2001")
    feeding.begin(url=url, job_id=job["id"], machine_id="2001", attempt=later.attempt,
                  lease_ttl_s=settings.lease_ttl_s)

    with pytest.raises(feeding.Behind):
        feeding.begin(url=url, job_id=job["id"], machine_id="2001", attempt=stale.attempt,
                      lease_ttl_s=settings.lease_ttl_s)

    [run] = client.get("/api/runs", params={"machine": "2001"}).json()
    assert run["state"] == "running", run


def test_a_runner_whose_claim_the_reaper_put_back_does_not_start_its_run(
        client, add_machines, settings) -> None:
    # Started by the stale runner, the run was fed with its target waiting, and the next
    # claim failed it as one whose worker stopped.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    job = start_run(client, "2001", stored(client)).json()
    stale = targets.begin(settings=settings, job_id=job["id"], machine_id="2001")
    assert stale.work is not None
    with db.session_scope(settings.resolved_database_url) as session:  # its leases ran out
        long_ago = utcnow() - timedelta(seconds=settings.lease_ttl_s * 4)
        session.execute(update(Target).where(Target.job_id == job["id"])
                        .values(lease_until=long_ago))
        session.execute(update(MachineLease).where(MachineLease.holder == stale.holder)
                        .values(expires_at=long_ago))
    reaper.reap(settings=settings)

    with pytest.raises(feeding.Behind):
        feeding.begin(url=settings.resolved_database_url, job_id=job["id"], machine_id="2001",
                      attempt=stale.work.attempt, lease_ttl_s=settings.lease_ttl_s)

    [run] = client.get("/api/runs", params={"machine": "2001"}).json()
    assert run["state"] == "queued", run


def test_a_refusal_by_a_run_that_confirmed_no_line_yet_says_so_not_line_0(
        client, add_machines, settings) -> None:
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    program = stored(client)
    first = start_run(client, "2001", program).json()
    feeding.begin(url=settings.resolved_database_url, job_id=first["id"], machine_id="2001",
                  attempt=1)

    said = start_run(client, "2001", program).json()["statusMsg"]

    assert "has a drip-feed run running (no line confirmed yet) (job" in said, said


@pytest.mark.parametrize(("kind", "field"), [("send", {"queue": True}),
                                            ("delete", {"from_line": 5})])
def test_a_drip_feed_runs_field_on_another_job_is_refused_naming_it(
        client, add_machines, kind: str, field: dict[str, Any]) -> None:
    # It was ignored: a send told to queue went at once, as if it had not been asked.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})

    answer = client.post("/api/jobs", json={"kind": kind, "machines": {"ids": ["2001"]},
                                            "fileName": "PART.NC", "content": "M30", **field})

    assert answer.status_code == 422 and answer.json()["errorCode"] == 20001
    assert answer.json()["statusMsg"] == f"{next(iter(field))}: for a dnc_run job only, " \
                                         f"not a {kind} job"
    assert client.get("/api/jobs").json() == []


def test_a_machine_whose_run_ended_takes_the_next_run(client, add_machines) -> None:
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    program = stored(client)
    first = start_run(client, "2001", program).json()
    client.post(f"/api/jobs/{first['id']}/stop")

    answer = start_run(client, "2001", program)

    assert answer.status_code == 202, answer.text


def a_run_stopped_as_its_worker_was_lost(client: Any, settings: Any) -> str:
    """A run begun on machine 2001, stopped, its worker lost before it saw the stop, and
    its target queued again by the reaper; returns the job's id."""
    job_id = start_run(client, "2001", stored(client)).json()["id"]
    url = settings.resolved_database_url
    assert targets.begin(settings=settings, job_id=job_id, machine_id="2001").work is not None
    feeding.begin(url=url, job_id=job_id, machine_id="2001", attempt=1)
    client.post(f"/api/jobs/{job_id}/stop")
    with db.session_scope(url) as session:  # its leases and its last write ran out
        long_ago = utcnow() - timedelta(seconds=settings.lease_ttl_s * 4)
        session.execute(update(Target).where(Target.job_id == job_id)
                        .values(lease_until=long_ago))
        session.execute(update(MachineLease).values(expires_at=long_ago))
        session.execute(update(Run).where(Run.job_id == job_id).values(updated_at=long_ago))
    reaper.reap(settings=settings)
    return job_id


def test_a_run_stopped_as_its_worker_was_lost_holds_its_machine_no_longer(
        client, add_machines, settings) -> None:
    # The runner that took its target up again cancelled it, and nothing ended the run:
    # every later run of the machine was refused, and dncq stop changed nothing.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    job_id = a_run_stopped_as_its_worker_was_lost(client, settings)
    targets.begin(settings=settings, job_id=job_id, machine_id="2001")  # finds it cancelled
    url = settings.resolved_database_url
    with db.session_scope(url) as session:  # a worker feeding it still would write it
        session.execute(update(Run).where(Run.job_id == job_id).values(updated_at=utcnow()))
    still_fed = start_run(client, "2001", stored(client))
    with db.session_scope(url) as session:
        session.execute(update(Run).where(Run.job_id == job_id).values(
            updated_at=utcnow() - timedelta(seconds=settings.lease_ttl_s * 2)))

    answer = start_run(client, "2001", stored(client))

    assert still_fed.status_code == 409
    assert answer.status_code == 202, answer.text
    [run] = client.get(f"/api/jobs/{job_id}").json()["runs"]
    assert run["state"] == "stopped"


def test_a_stop_of_a_cancelled_job_ends_its_run_whose_worker_was_lost(
        client, add_machines, settings) -> None:
    # The stop changed nothing: the run stayed running, in dncq runs too, until the next run
    # asked of its machine or a runner's follow-up closed it.
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    job_id = a_run_stopped_as_its_worker_was_lost(client, settings)
    targets.begin(settings=settings, job_id=job_id, machine_id="2001")  # finds it cancelled

    answer = client.post(f"/api/jobs/{job_id}/stop")

    assert answer.json()["stopping"] == 1
    [run] = client.get(f"/api/jobs/{job_id}").json()["runs"]
    assert run["state"] == "stopped" and run["endedAt"] is not None


def test_a_runner_that_finds_a_lost_runs_job_stopped_ends_its_run(
        client, add_machines, settings) -> None:
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    job_id = a_run_stopped_as_its_worker_was_lost(client, settings)

    runner.run_machine(settings, job_id, "2001")  # the task the reaper queued

    [run] = client.get(f"/api/jobs/{job_id}").json()["runs"]
    assert run["state"] == "stopped"


def test_a_run_whose_machine_was_removed_before_it_started_ends_failed_saying_so(
        client, add_machines, settings) -> None:
    add_machines({"id": "2001", "name": "DNC-H", "model": "Mock"})
    job_id = start_run(client, "2001", stored(client)).json()["id"]
    with db.session_scope(settings.resolved_database_url) as session:
        registry.delete(session=session, machine_id="2001")

    runner.run_machine(settings, job_id, "2001")

    [run] = client.get(f"/api/jobs/{job_id}").json()["runs"]
    assert run["state"] == "failed" and "2001" in run["message"]


RACED_MACHINES = 5
RACERS = 4  # runs asked at once of each machine


def test_runs_asked_at_once_of_one_machine_queue_one_and_refuse_the_others(
        settings, database_url: str) -> None:
    raced = settings.model_copy(update={"database_url": database_url})
    machines = [f"race{i}" for i in range(RACED_MACHINES)]
    with db.session_scope(database_url) as session:
        for machine_id in machines:
            registry.upsert(session=session, machine_in=registry.MachineIn(
                id=machine_id, name="Mill", model="Mock"), data_dir=settings.data_dir)
    answers: dict[str, list[int]] = {m: [] for m in machines}
    with serving(create_app(raced)) as server:
        def api() -> httpx.Client:
            return httpx.Client(base_url=server.url, headers={"X-Api-Key": API_KEY}, timeout=60)

        with api() as http:
            program = stored(http)
        at_once = threading.Barrier(RACERS)

        def ask(machine_id: str) -> None:
            with api() as http:
                at_once.wait()
                answers[machine_id].append(start_run(http, machine_id, program).status_code)

        for machine_id in machines:
            threads = [threading.Thread(target=ask, args=(machine_id,)) for _ in range(RACERS)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()

    assert {m: sorted(a) for m, a in answers.items()} == {
        m: [202] + [409] * (RACERS - 1) for m in machines}
    with db.session_scope(database_url) as session:
        assert sorted(session.scalars(select(Run.machine_id).where(
            Run.machine_id.in_(machines)))) == machines


def test_an_attempt_that_found_the_control_not_ready_waits_unless_a_stop_came_meanwhile(
        client, add_machines, settings) -> None:
    """The runner's side, driven by hand (no worker here): the attempt begins the run, the
    control turns out not to be ready, nothing was sent."""
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})
    job = start_run(client, "m1", stored(client)).json()
    url = settings.resolved_database_url

    ticket = feeding.begin(url=url, job_id=job["id"], machine_id="m1", attempt=1)
    assert feeding.not_started(url=url, run_id=ticket.run_id, message="not in DNC mode") is None
    [run] = client.get(f"/api/jobs/{job['id']}").json()["runs"]
    assert (run["state"], run["message"]) == ("queued", "not in DNC mode")

    ticket = feeding.begin(url=url, job_id=job["id"], machine_id="m1", attempt=2)  # the next one
    assert client.post(f"/api/jobs/{job['id']}/stop").json()["stopping"] == 1
    assert feeding.not_started(url=url, run_id=ticket.run_id,
                               message="not in DNC mode") == "stopped by api before it started"
    [run] = client.get(f"/api/jobs/{job['id']}").json()["runs"]
    assert run["state"] == "cancelled"


def test_a_run_that_never_started_ends_with_the_reason_its_attempts_met(
        client, add_machines, settings) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})
    job = start_run(client, "m1", stored(client)).json()
    url = settings.resolved_database_url
    why = "the control refused DNC: the control is in MEM mode, not DNC"
    ticket = feeding.begin(url=url, job_id=job["id"], machine_id="m1", attempt=1)
    feeding.not_started(url=url, run_id=ticket.run_id, message=why)
    with db.session_scope(url) as session:  # its last attempt failed: as the runner ends it
        session.execute(update(Target).where(Target.job_id == job["id"]).values(
            state=TargetState.FAILED, error_code=int(ErrorCode.MACHINE_BUSY),
            error_msg="Machine is busy.", status_msg=why))

    assert runs.close_unstarted(url=url, job_id=job["id"]) == 1

    [run] = client.get(f"/api/jobs/{job['id']}").json()["runs"]
    assert (run["state"], run["message"]) == ("failed", why)


def test_a_stop_between_a_runners_claim_and_the_runs_start_keeps_it_from_starting(
        client, add_machines, settings) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})
    job = start_run(client, "m1", stored(client)).json()
    url = settings.resolved_database_url
    with db.session_scope(url) as session:  # a runner claimed the target, as its lease says
        session.execute(update(Target).where(Target.job_id == job["id"])
                        .values(state=TargetState.RUNNING, attempts=1))

    client.post(f"/api/jobs/{job['id']}/stop")

    with pytest.raises(ContractError) as refused:
        feeding.begin(url=url, job_id=job["id"], machine_id="m1", attempt=1)
    assert refused.value.code is ErrorCode.CANCELLED


class _RefusingAtLine:
    """A machine's files whose control takes `lines` lines, runs the first, then refuses: an
    ERROR reply in the middle of a run (or before it, at 0), which the simulator never
    sends, so it stands in for the control here."""

    encoding = "ascii"

    def __init__(self, lines: int) -> None:
        self.lines = lines

    def drip_feed(self, name: str, lines: Any, *, total_lines: int | None, on_line: Any,
                  should_stop: Any) -> Any:
        for sent, _ in enumerate(lines):
            if sent == self.lines:
                break
            on_line(1, sent + 1)  # still running line 1 while it holds more
        raise ContractError(ErrorCode.INTERNAL_ERROR, "the control refused: overheated")


@pytest.mark.parametrize(("refused_at", "said"), [
    (3, "the control refused: overheated (at line 1); the machine held the lines up to 3 and "
        "may have run them: restart with --from-line at the line it shows (1 to 3)"),
    (0, "the control refused: overheated (before its first line)")])  # nothing ran
def test_a_run_refused_by_its_control_says_where_and_names_the_lines_to_restart_between(
        client, add_machines, settings, refused_at: int, said: str) -> None:
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})
    job = start_run(client, "m1", stored(client)).json()
    started = targets.begin(settings=settings, job_id=job["id"], machine_id="m1")
    assert started.work is not None

    refusing: Any = _RefusingAtLine(refused_at)
    state, error, _ = drip_run.execute(settings, refusing, started.work)

    assert state is TargetState.FAILED and error is not None and not error.transient
    [run] = client.get(f"/api/jobs/{job['id']}").json()["runs"]
    assert run["message"] == said


class _NotReadyAsStopped:
    """A machine's files whose control is not ready (a transient refusal before the first
    line) while the run's stop comes in at that moment."""

    encoding = "ascii"

    def __init__(self, stop: Any) -> None:
        self.stop = stop

    def drip_feed(self, name: str, lines: Any, *, total_lines: int | None, on_line: Any,
                  should_stop: Any) -> Any:
        self.stop()
        raise ContractError(ErrorCode.MACHINE_BUSY, "the control is in MEM mode, not DNC")


def test_a_run_stopped_as_its_control_was_not_ready_says_who_stopped_it_before_it_started(
        client, add_machines, settings) -> None:
    # Its target said "stopped before it started", naming no one, where its job named alice.
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})
    job = start_run(client, "m1", stored(client)).json()
    started = targets.begin(settings=settings, job_id=job["id"], machine_id="m1")
    assert started.work is not None

    files: Any = _NotReadyAsStopped(lambda: client.post(f"/api/jobs/{job['id']}/stop",
                                                        params={"by": "alice"}))
    state, error, _ = drip_run.execute(settings, files, started.work)

    assert state is TargetState.CANCELLED and error is not None
    assert (error.code, error.status_msg) == (ErrorCode.CANCELLED,
                                              "stopped by alice before it started")
    [run] = client.get(f"/api/jobs/{job['id']}").json()["runs"]
    assert (run["state"], run["message"]) == ("cancelled", "stopped by alice before it started")


def test_a_run_whose_control_sent_a_bad_frame_before_its_first_line_is_not_tried_again(
        client, add_machines, settings) -> None:
    # Retried as a control not ready, it met the same frame at every attempt.
    listener = socket.create_server(("127.0.0.1", 0))

    def control() -> None:  # takes the run, then answers its query too short
        conn, _ = listener.accept()
        with conn:
            stream = conn.makefile("rb")
            start = wire.read_frame(stream.read)  # UPDATE_FILE_DNC
            conn.sendall(wire.encode(wire.Command.OK, start.request_id,
                                     wire.uint_payload(7, 4)))
            query = wire.read_frame(stream.read)  # QUERY_FILE_DNC
            conn.sendall(wire.encode(wire.Command.GET_FILE_DNC, query.request_id,
                                     b"\0\0\0\1"))
            wire.read_frame(stream.read)  # its ERROR BAD_FRAME

    serving = threading.Thread(target=control, daemon=True)
    serving.start()
    [spec] = add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F",
                           "transport": "dnc", "options": {
                               "host": "127.0.0.1", "port": listener.getsockname()[1],
                               "timeout_s": 5, "heartbeat_interval_s": 60}})
    job = start_run(client, "2001", stored(client)).json()
    started = targets.begin(settings=settings, job_id=job["id"], machine_id="2001")
    assert started.work is not None
    files = door.open_files(spec, data_dir=settings.data_dir)
    try:
        state, error, _ = drip_run.execute(settings, files, started.work)
    finally:
        files.close()
        serving.join(5)
        listener.close()

    assert state is TargetState.FAILED and error is not None and not error.transient
    [run] = client.get(f"/api/jobs/{job['id']}").json()["runs"]
    assert (run["state"], run["message"]) == (
        "failed", "the control sent a bad GET_FILE_DNC (payload too short) (before its first "
                  "line)")


@pytest.fixture
def restartable_postgres() -> Iterator[PostgresServer]:
    """A PostgreSQL server of the test's own, which the test may stop and start."""
    with postgres_of_its_own() as server:
        yield server


def a_run_begun(settings: Any, server: PostgresServer, *,
                lease_ttl_s: float = 2.0) -> tuple[Any, str, Any]:
    """Settings on `server` (retries at once; a run's end waits half `lease_ttl_s` for a
    lost database), and a drip-feed job on a Mock machine whose first attempt has begun:
    (settings, job id, the attempt's start)."""
    s = settings.model_copy(update={"database_url": server.url, "lease_ttl_s": lease_ttl_s,
                                    "retry_base_s": 0.0, "retry_max_s": 0.0})
    url = s.resolved_database_url
    db.upgrade(url)
    with db.session_scope(url) as session:
        registry.upsert(session=session, data_dir=s.data_dir, machine_in=registry.MachineIn(
            id="m1", name="Mill", model="Mock"))
        job_id = runs.submit(session=session, settings=s, machine_ids=["m1"],
                             program=programs.store(s, iter([PROGRAM])), file_name="PART.NC").id
    started = targets.begin(settings=s, job_id=job_id, machine_id="m1")
    assert started.work is not None and started.holder is not None and started.spec is not None
    return s, job_id, started


class _LosingTheDatabase:
    """A machine's files whose control takes four lines and runs two, while the database
    stops after the first. Then either the link is lost (the run's end cannot be recorded),
    or the feed itself meets the database gone, back by the time the run's end is recorded."""

    encoding = "ascii"

    def __init__(self, server: PostgresServer, *, back_before_the_end: bool) -> None:
        self.server, self.back_before_the_end = server, back_before_the_end

    def drip_feed(self, name: str, lines: Any, *, total_lines: int | None, on_line: Any,
                  should_stop: Any) -> Any:
        for sent, _ in enumerate(lines, start=1):
            on_line(min(sent, 2), sent)
            if sent == 1:
                self.server.stop()
        if self.back_before_the_end:
            try:
                with db.session_scope(self.server.url) as session:
                    session.execute(text("SELECT 1"))
            finally:
                self.server.start()
        raise LinkLost("the link stayed down", last_line=2, lines_sent=4)


@pytest.mark.parametrize("back_before_the_end", [False, True])
def test_a_run_that_lost_its_database_after_its_first_line_ends_with_its_one_attempt(
        settings, restartable_postgres, back_before_the_end: bool) -> None:
    # It was retried as a lost database is, and the retry refused at once: tries 2. A
    # database back in time to record the run's end made it "the run ended unexpectedly".
    s, job_id, started = a_run_begun(settings, restartable_postgres)
    url = s.resolved_database_url

    losing: Any = _LosingTheDatabase(restartable_postgres,
                                     back_before_the_end=back_before_the_end)
    outcome = runner.attempt(s, started.spec, started.work, losing)
    if not back_before_the_end:
        restartable_postgres.start()
    done = targets.finish(settings=s, work=started.work, holder=started.holder,
                          error=outcome.error, state=outcome.state)
    runs.close_unstarted(url=url, job_id=job_id)  # as the runner does once it is recorded

    assert done.retry_in_s is None
    with db.session_scope(url) as session:
        target = session.scalars(select(Target).where(Target.job_id == job_id)).one()
        run = session.scalars(select(Run).where(Run.job_id == job_id)).one()
        assert (target.state, target.attempts) == (TargetState.FAILED, 1)
        assert run.state is RunState.FAILED and run.message == target.status_msg
        # What ended the run for the machine (its feed met the database gone, or its link
        # was lost), and where it was, as a lost link says it.
        why = "database unavailable (OperationalError) at line 2" if back_before_the_end \
            else "link lost at line 2: the link stayed down"
        assert run.message == (
            f"{why}; the machine held the lines up to 4 and may have run them: restart with "
            "--from-line at the line it shows (2 to 4)")


def test_a_run_whose_feed_met_the_database_lost_records_the_lines_its_message_names(
        settings, restartable_postgres) -> None:
    # Its end was left to the runner, which closed it with its target's words: "at line 2,
    # held up to 4", beside the line counts last written before the database was lost.
    s, job_id, started = a_run_begun(settings, restartable_postgres)
    url = s.resolved_database_url

    losing: Any = _LosingTheDatabase(restartable_postgres, back_before_the_end=True)
    outcome = runner.attempt(s, started.spec, started.work, losing)
    targets.finish(settings=s, work=started.work, holder=started.holder,
                   error=outcome.error, state=outcome.state)
    runs.close_unstarted(url=url, job_id=job_id)  # as the runner does once it is recorded

    with db.session_scope(url) as session:
        run = session.scalars(select(Run).where(Run.job_id == job_id)).one()
        assert run.message is not None and run.message.startswith(
            "database unavailable (OperationalError) at line 2; the machine held the lines "
            "up to 4")
        assert (run.state, run.last_line, run.lines_sent) == (RunState.FAILED, 2, 4)


class _RunToItsEndWithTheDatabaseGone:
    """A machine's files whose control runs the whole program, while the database stops
    after the first line and is still down when the run's end is to be recorded."""

    encoding = "ascii"

    def __init__(self, server: PostgresServer) -> None:
        self.server = server

    def drip_feed(self, name: str, lines: Any, *, total_lines: int | None, on_line: Any,
                  should_stop: Any) -> Any:
        sent = 0
        for sent, _ in enumerate(lines, start=1):
            on_line(sent, sent)
            if sent == 1:
                self.server.stop()
        return DripResult(lines_sent=sent, last_line=sent, stopped=False)


def test_a_run_that_ran_to_its_end_while_the_database_was_lost_succeeded(
        settings, restartable_postgres) -> None:
    # The end of the run could not be recorded, and the program that ran to its end was
    # reported failed, with where to restart it: the operator would cut its tail again.
    s, job_id, started = a_run_begun(settings, restartable_postgres)
    url = s.resolved_database_url

    feed: Any = _RunToItsEndWithTheDatabaseGone(restartable_postgres)
    outcome = runner.attempt(s, started.spec, started.work, feed)
    restartable_postgres.start()
    targets.finish(settings=s, work=started.work, holder=started.holder,
                   error=outcome.error, state=outcome.state, status_msg=outcome.status_msg)
    runs.close_unstarted(url=url, job_id=job_id)  # as the runner does once it is recorded

    assert (outcome.state, outcome.error) == (TargetState.SUCCEEDED, None)
    with db.session_scope(url) as session:
        target = session.scalars(select(Target).where(Target.job_id == job_id)).one()
        run = session.scalars(select(Run).where(Run.job_id == job_id)).one()
        assert target.state is TargetState.SUCCEEDED
        assert (run.state, run.message) == (RunState.SUCCEEDED, "ran to line 4")


class _DatabaseLostForAFewSecondsAtTheEnd:
    """A machine's files whose control runs the whole program; the database stops as the
    last line is confirmed and is started again a few seconds later."""

    encoding = "ascii"

    def __init__(self, server: PostgresServer) -> None:
        self.server = server
        self.restart = threading.Timer(2.0, server.start)

    def drip_feed(self, name: str, lines: Any, *, total_lines: int | None, on_line: Any,
                  should_stop: Any) -> Any:
        sent = 0
        for sent, _ in enumerate(lines, start=1):
            on_line(sent, sent)
        self.server.stop()
        self.restart.start()
        return DripResult(lines_sent=sent, last_line=sent, stopped=False)


def test_a_run_that_ended_while_the_database_was_lost_for_a_few_seconds_is_recorded(
        settings, restartable_postgres) -> None:
    # Neither the run's end nor its target could be recorded: the target stayed running
    # until its lease ran out, and the next attempt failed the program that ran to its end.
    s, job_id, started = a_run_begun(settings, restartable_postgres, lease_ttl_s=30.0)
    url = s.resolved_database_url

    feed: Any = _DatabaseLostForAFewSecondsAtTheEnd(restartable_postgres)
    try:
        outcome = runner.attempt(s, started.spec, started.work, feed)
        targets.finish(settings=s, work=started.work, holder=started.holder,
                       error=outcome.error, state=outcome.state, status_msg=outcome.status_msg)
    finally:
        feed.restart.join()

    with db.session_scope(url) as session:
        target = session.scalars(select(Target).where(Target.job_id == job_id)).one()
        run = session.scalars(select(Run).where(Run.job_id == job_id)).one()
        assert (target.state, target.status_msg) == (TargetState.SUCCEEDED, "ran to line 4")
        assert (run.state, run.message, run.last_line, run.lines_sent) == (
            RunState.SUCCEEDED, "ran to line 4", 4, 4)


class _DatabaseLostBeforeTheFirstLine:
    """A machine's files whose feed meets the database gone before it sends a line; the
    database is back by the time the attempt's end is recorded."""

    encoding = "ascii"

    def __init__(self, server: PostgresServer) -> None:
        self.server = server

    def drip_feed(self, name: str, lines: Any, *, total_lines: int | None, on_line: Any,
                  should_stop: Any) -> Any:
        self.server.stop()
        try:
            with db.session_scope(self.server.url) as session:
                session.execute(text("SELECT 1"))
        finally:
            self.server.start()
        raise AssertionError("the database answered while stopped")


def test_a_run_that_lost_its_database_before_its_first_line_is_tried_again(
        settings, restartable_postgres) -> None:
    # The machine saw nothing, as docs/dnc-runs.md says of a run that could not start; the
    # run was recorded "ended unexpectedly", and the next attempt was refused at once.
    s, job_id, started = a_run_begun(settings, restartable_postgres)
    url = s.resolved_database_url

    feed: Any = _DatabaseLostBeforeTheFirstLine(restartable_postgres)
    outcome = runner.attempt(s, started.spec, started.work, feed)

    assert outcome.error is not None and outcome.error.transient
    done = targets.finish(settings=s, work=started.work, holder=started.holder,
                          error=outcome.error, state=outcome.state)
    assert done.retry_in_s is not None  # tried again
    again = feeding.begin(url=url, job_id=job_id, machine_id="m1", attempt=2)  # the next starts
    assert again.start_line == 1 and again.lines_total == 4


class _StoppedWithTheDatabaseGone:
    """A machine's files whose run is stopped on request after its first line, and the
    database lost before the stop's end is recorded."""

    encoding = "ascii"

    def __init__(self, server: PostgresServer, settings: Any, job_id: str) -> None:
        self.server, self.settings, self.job_id = server, settings, job_id

    def drip_feed(self, name: str, lines: Any, *, total_lines: int | None, on_line: Any,
                  should_stop: Any) -> Any:
        next(iter(lines))
        on_line(1, 1)
        with db.session_scope(self.server.url) as session:  # `dncq stop`
            runs.request_stop(session=session, settings=self.settings, job_id=self.job_id,
                              stopped_by="alice")
        self.server.stop()
        return DripResult(lines_sent=1, last_line=1, stopped=True)


def test_a_run_stopped_while_the_database_was_lost_ends_stopped(
        settings, restartable_postgres) -> None:
    # Its end could not be recorded, and the run stayed running for ever (`dncq run` with it).
    s, job_id, started = a_run_begun(settings, restartable_postgres)
    url = s.resolved_database_url

    feed: Any = _StoppedWithTheDatabaseGone(restartable_postgres, s, job_id)
    outcome = runner.attempt(s, started.spec, started.work, feed)
    restartable_postgres.start()
    targets.finish(settings=s, work=started.work, holder=started.holder,
                   error=outcome.error, state=outcome.state, status_msg=outcome.status_msg)
    runs.close_unstarted(url=url, job_id=job_id)  # as the runner does once it is recorded

    with db.session_scope(url) as session:
        target = session.scalars(select(Target).where(Target.job_id == job_id)).one()
        run = session.scalars(select(Run).where(Run.job_id == job_id)).one()
        assert target.state is TargetState.CANCELLED
        assert run.state is RunState.STOPPED and run.ended_at is not None
        assert run.message == target.status_msg == (
            "stopped on request at line 1; the machine was reset")
