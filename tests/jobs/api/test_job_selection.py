"""`POST /api/jobs` with a `machines` selection that names ids or tags nobody has."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sqlalchemy import event, insert

from jobs import db, rollout
from jobs.models import Machine
from jobs.settings import Settings


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


@pytest.mark.parametrize("machines", [{}, {"ids": []}, {"all": False}])
def test_a_selection_of_no_machine_is_refused_whole_with_422(client, fleet, machines) -> None:
    response = client.post("/api/jobs", json={"kind": "delete", "fileName": "P.nc",
                                              "machines": machines})

    assert response.status_code == 422  # not a 200 a client would take for a job made
    assert response.json()["errorCode"] == 20001
    assert response.json()["statusMsg"] == "no machine selected: give targets, ids, tags or all"
    assert client.get("/api/jobs").json() == []


def test_an_id_one_character_off_is_meant_before_others_as_close(client, add_machines):
    add_machines(*({"id": m, "name": m, "model": "Mock"} for m in ("1001", "1016", "2001")))

    response = client.post("/api/jobs", json={"kind": "delete", "fileName": "P.nc",
                                              "machines": {"ids": ["1O01"]}})

    assert response.json()["statusMsg"] == ("no machine 1O01 (did you mean 1001?); "
                                            "nothing was queued")


@pytest.mark.parametrize(("largest_hinted", "said"), [
    (3, "no machine 1O01 (did you mean 1001?); nothing was queued"),
    (2, "no machine 1O01; nothing was queued")])  # too many ids to compare on every miss
def test_a_mistyped_id_is_hinted_only_in_a_fleet_small_enough(
        client, add_machines, monkeypatch, largest_hinted: int, said: str):
    from jobs.fleet import registry
    add_machines(*({"id": m, "name": m, "model": "Mock"} for m in ("1001", "1016", "2001")))
    monkeypatch.setattr(registry, "HINTED_FLEET", largest_hinted)

    response = client.post("/api/jobs", json={"kind": "delete", "fileName": "P.nc",
                                              "machines": {"ids": ["1O01"]}})

    assert response.json()["statusMsg"] == said


def test_only_the_first_missing_ids_are_hinted(client, fleet, monkeypatch):
    from jobs.fleet import registry
    monkeypatch.setattr(registry, "HINTED_NAMES", 1)

    response = client.post("/api/jobs", json={"kind": "delete", "fileName": "P.nc",
                                              "machines": {"ids": ["1O10", "1O15"]}})

    assert response.json()["statusMsg"] == ("no machine 1O10 (did you mean 1010?), 1O15; "
                                            "nothing was queued")


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


# -- a request's cost does not grow with the fleet ----------------------------------------

LARGE_FLEET = 3_000


@pytest.fixture
def large_fleet(settings: Settings, fleet: None) -> None:
    """Thousands of registered machines beside the two above (rows only: never run)."""
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(insert(Machine), [
            {"id": f"big-{n:05d}", "name": f"Big {n}", "model": "Mock", "transport": "mock",
             "tags": ["hall"]} for n in range(LARGE_FLEET)])


@pytest.fixture
def machines_read() -> Iterator[list[str]]:
    """The ids of the machines read whole from the database while the test runs."""
    read: list[str] = []

    def loaded(machine: Machine, _context: object) -> None:
        read.append(machine.id)

    event.listen(Machine, "load", loaded)
    yield read
    event.remove(Machine, "load", loaded)


def test_a_job_naming_one_machine_of_a_large_fleet_reads_that_machine_only(
        client, large_fleet, machines_read):
    response = client.post("/api/jobs", json={"kind": "delete", "fileName": "P.nc",
                                              "machines": {"ids": ["1010"]}})

    assert response.status_code == 202, response.text
    assert response.json()["total"] == 1
    assert set(machines_read) <= {"1010"}


def test_an_unknown_id_in_a_large_fleet_is_still_refused_with_the_one_meant(
        client, large_fleet):
    response = client.post("/api/jobs", json={"kind": "delete", "fileName": "P.nc",
                                              "machines": {"ids": ["1O15"]}})

    assert response.status_code == 422
    assert response.json()["statusMsg"] == ("no machine 1O15 (did you mean 1015?); "
                                            "nothing was queued")


def test_a_dry_run_and_text_in_each_machine_s_encoding_read_only_the_machines_named(
        client, large_fleet, machines_read):
    plan = client.post("/api/jobs", json={"kind": "send", "fileName": "P.nc", "dry_run": True,
                                          "content": "(Größe)\nG0 X0\n",
                                          "machines": {"ids": ["1015"]}})
    sent = client.post("/api/jobs", json={"kind": "send", "fileName": "Q.nc",
                                          "content": "(Größe)\nG0 X0\n",
                                          "machines": {"ids": ["1010"]}})

    assert (plan.status_code, sent.status_code) == (202, 202), (plan.text, sent.text)
    assert plan.json()["dryRun"] and sent.json()["total"] == 1
    assert set(machines_read) <= {"1010", "1015"}


def test_a_fleet_wide_selection_lists_named_ids_first_then_the_rest_by_id_without_reading_machines(
        settings, large_fleet, machines_read):
    selector = rollout.Selector(ids=["big-00007", "1015"], tags=["hall"])
    with db.session_scope(settings.resolved_database_url) as session:
        chosen = [t.machineID for t in rollout.select_targets(
            session=session, selector=selector, file_name="P.nc", dir_at_cnc=None, sub_dir=None)]
        everyone = [t.machineID for t in rollout.select_targets(
            session=session, selector=rollout.Selector(all=True), file_name="P.nc",
            dir_at_cnc=None, sub_dir=None)]

    hall = [f"big-{n:05d}" for n in range(LARGE_FLEET)]
    assert chosen == ["big-00007", "1015"] + [m for m in hall if m != "big-00007"]
    assert everyone == ["1010", "1015"] + hall
    assert machines_read == []
