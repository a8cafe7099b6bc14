"""`POST /api/jobs` with a `machines` selection that names ids or tags nobody has."""

from __future__ import annotations

import pytest


@pytest.fixture
def fleet(add_machines) -> None:
    add_machines({"id": "1010", "name": "A", "model": "Mock", "tags": ["lathes"]},
                 {"id": "1015", "name": "B", "model": "Mock"})


def test_an_unknown_id_is_refused_whole_with_10003_naming_it_and_the_one_meant(client, fleet):
    response = client.post("/api/jobs", json={"kind": "delete", "fileName": "P.nc",
                                              "machines": {"ids": ["1010", "1O15"]}})

    assert response.status_code == 422
    assert response.json()["errorCode"] == 10003
    assert response.json()["statusMsg"] == ("no machine 1O15 (did you mean 1015?); "
                                            "nothing was queued")
    assert client.get("/api/jobs").json() == []


def test_a_tag_no_machine_carries_is_refused_with_20001_naming_it(client, fleet):
    response = client.post("/api/jobs", json={"kind": "backup", "machines": {"tags": ["mills"]}})

    assert response.status_code == 422
    assert response.json()["errorCode"] == 20001
    assert "no machine tagged mills" in response.json()["statusMsg"]
    assert client.get("/api/jobs").json() == []


def test_allow_unknown_queues_the_job_with_the_unknown_id_as_a_failed_target(client, fleet):
    job = client.post("/api/jobs", json={"kind": "delete", "fileName": "P.nc",
                                         "machines": {"ids": ["1O15", "1010"]},
                                         "allow_unknown": True}).json()

    targets = client.get(f"/api/jobs/{job['id']}").json()["targets"]

    assert [(t["machineID"], t["errorCode"]) for t in targets][0] == ("1O15", 10003)


def test_an_unknown_tag_with_allow_unknown_and_nothing_else_is_still_refused_naming_it(
        client, fleet):
    response = client.post("/api/jobs", json={"kind": "backup", "allow_unknown": True,
                                              "machines": {"tags": ["lathe"]}})

    assert response.status_code == 422
    assert "no machine tagged lathe (did you mean lathes?)" in response.json()["statusMsg"]


def test_a_dry_run_lists_the_unknown_ids_and_tags(client, fleet):
    plan = client.post("/api/jobs", json={"kind": "backup", "dry_run": True,
                                          "machines": {"ids": ["1010", "1099"],
                                                       "tags": ["mills"]}}).json()

    assert plan["unknown"]["ids"] == ["1099"] and plan["unknown"]["tags"] == ["mills"]
    assert [t["machineID"] for t in plan["targets"]] == ["1010", "1099"]
