"""Lists filtered by a machine: one nobody registered that no row holds is refused (404, 10003)
naming the id it was likely typed for, not answered with an empty list; one removed from the
registry since is still known by its jobs and runs."""

from __future__ import annotations

import pytest

from tests.jobs.helpers import wait_done

LISTS = ["/api/jobs", "/api/runs", "/api/inbox", "/api/library/assignments"]


@pytest.mark.parametrize("path", LISTS)
def test_a_list_filtered_by_a_mistyped_machine_is_refused_naming_the_machine_meant(
        client, add_machines, path):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    listed = client.get(path, params={"machine": "1O10"})  # a letter O for the 0

    assert listed.status_code == 404
    assert listed.json() == {"errorCode": 10003, "errorMsg": "Machine ID does not exist.",
                             "statusMsg": "Invalid MachineID (1O10) (did you mean 1010?)"}


@pytest.mark.parametrize("path", LISTS)
def test_a_list_filtered_by_a_registered_machine_with_nothing_of_its_own_is_empty(
        client, add_machines, path):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    listed = client.get(path, params={"machine": "1010"})

    assert listed.status_code == 200, listed.text
    assert listed.json() == []


def test_the_machine_list_filtered_by_a_tag_no_machine_carries_is_refused_naming_the_tag_meant(
        client, add_machines):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock", "tags": ["lathes"]})

    mistyped = client.get("/api/machines", params={"tag": "lathe"})
    carried = client.get("/api/machines", params={"tag": "lathes"})

    assert mistyped.status_code == 422
    assert mistyped.json()["statusMsg"] == "no machine tagged lathe (did you mean lathes?)"
    assert [m["id"] for m in carried.json()] == ["1010"]


def test_the_jobs_and_runs_of_a_machine_removed_since_are_still_listed(
        queue_client, add_machines):
    add_machines({"id": "m1", "name": "Mill", "model": "Mock"})  # no DNC link: the run fails
    program = queue_client.post("/api/programs", content=b"O0010\nM30\n",
                                headers={"content-type": "application/octet-stream"}).json()
    job = queue_client.post("/api/jobs", json={
        "kind": "dnc_run", "machines": {"ids": ["m1"]}, "program": program["id"],
        "fileName": "PART.NC"}).json()
    [run] = wait_done(queue_client, job["id"])["runs"]
    assert queue_client.delete("/api/machines/m1").status_code == 204

    jobs = queue_client.get("/api/jobs", params={"machine": "m1"})
    runs = queue_client.get("/api/runs", params={"machine": "m1"})

    assert [j["id"] for j in jobs.json()] == [job["id"]]
    assert [r["id"] for r in runs.json()] == [run["id"]]
