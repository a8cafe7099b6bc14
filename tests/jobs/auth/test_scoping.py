"""An operator's machine list: a request naming a machine outside it is refused whole with
403 and the machines named; its own machines are served."""

from __future__ import annotations

from typing import Any

import pytest

from jobs.auth.roles import Role

SEND = {"content": "%\nO1000\n%\n"}


@pytest.fixture
def operator(make_key) -> dict[str, str]:
    """The headers of an operator key on machine 1010 only."""
    return {"X-Api-Key": make_key(Role.OPERATOR, machines=["1010"], name="cell-1")}


def test_an_operator_sends_to_its_own_machine(api, operator) -> None:
    answer = api.post("/api/cnc/sendFile?machineID=1010&fileName=O1000", json=SEND,
                      headers=operator)

    assert answer.json() == {"errorCode": 0, "errorMsg": "Success"}


def test_an_operator_is_refused_a_machine_outside_its_list_with_the_reason(api,
                                                                            operator) -> None:
    answer = api.post("/api/cnc/sendFile?machineID=1011&fileName=O1000", json=SEND,
                      headers=operator)

    assert answer.status_code == 403
    assert answer.json()["statusMsg"] == ("you (key:cell-1) may not change machine 1011; "
                                          "your machines: 1010")


def test_the_contracts_changing_gets_are_scoped_too(api, operator) -> None:
    answer = api.get("/api/cnc/deleteFile?machineID=1011&fileName=O1000", headers=operator)

    assert answer.status_code == 403


def test_an_operator_reads_every_machine(api, operator) -> None:
    answer = api.get("/api/cnc/readProgramList?machineID=1011", headers=operator)

    assert answer.status_code == 200 and "programs" in answer.json()


def test_a_batch_with_one_target_outside_the_list_is_refused_whole(api, operator,
                                                                   settings) -> None:
    targets = [{"machineID": "1010", "fileName": "O2000"},
               {"machineID": "1011", "fileName": "O2000"}]

    answer = api.post("/api/cnc/batchSendFile", json={**SEND, "targets": targets},
                      headers=operator)

    assert answer.status_code == 403
    assert "machine 1011" in answer.json()["statusMsg"]
    assert api.get("/api/jobs", headers=operator).json() == []  # nothing was queued


def test_a_batch_delete_on_its_own_machines_is_taken(api, operator) -> None:
    answer = api.post("/api/cnc/batchDeleteFile", json=[{"machineID": "1010",
                                                         "fileName": "O2000"}],
                      headers=operator)

    assert answer.status_code == 200 and len(answer.json()) == 1


def test_a_drip_feed_run_on_a_machine_outside_the_list_is_refused(api, operator) -> None:
    answer = api.post("/api/jobs", json={"kind": "dnc_run", "program": "0" * 64,
                                         "machines": {"ids": ["1011"]}}, headers=operator)

    assert answer.status_code == 403
    assert "machine 1011" in answer.json()["statusMsg"]


def test_a_drip_feed_run_selected_by_tag_is_refused_when_a_tagged_machine_is_outside(
        api, operator, add_machines) -> None:
    add_machines({"id": "2020", "name": "Tagged", "model": "Mock", "tags": ["cell"]})

    answer = api.post("/api/jobs", json={"kind": "dnc_run", "program": "0" * 64,
                                         "machines": {"tags": ["cell"]}}, headers=operator)

    assert answer.status_code == 403


def test_an_operator_may_not_start_a_rollout_even_on_its_machine(api, operator) -> None:
    answer = api.post("/api/jobs", json={"kind": "send", "content": "x", "targets": [
        {"machineID": "1010", "fileName": "O1"}]}, headers=operator)

    assert answer.status_code == 403
    assert "a send job needs the programmer role" in answer.json()["statusMsg"]


def test_a_restore_onto_a_machine_outside_the_list_is_refused(api, operator) -> None:
    answer = api.post("/api/backups/any/restore", json={"machine": "1010", "to": "1011"},
                      headers=operator)

    assert answer.status_code == 403


def _run_job(settings, machine_id: str) -> str:
    """A drip-feed run job recorded on `machine_id` (not started: no worker here)."""
    from jobs import db
    from jobs.models import Job, JobKind, Target

    with db.session_scope(settings.resolved_database_url) as session:
        session.add(Job(id=f"run-{machine_id}", kind=JobKind.DNC_RUN, targets=[
            Target(position=0, machine_id=machine_id)]))
    return f"run-{machine_id}"


def test_an_operator_stops_a_run_on_its_machine_but_not_on_another(api, operator,
                                                                   settings) -> None:
    own, other = _run_job(settings, "1010"), _run_job(settings, "1011")

    stopped = api.post(f"/api/jobs/{own}/stop", headers=operator)
    refused = api.post(f"/api/jobs/{other}/stop", headers=operator)

    assert stopped.status_code == 200
    assert refused.status_code == 403 and "machine 1011" in refused.json()["statusMsg"]


def test_an_operator_cancels_a_run_on_its_machine_but_not_on_another(api, operator,
                                                                     settings) -> None:
    own, other = _run_job(settings, "1010"), _run_job(settings, "1011")

    assert api.post(f"/api/jobs/{own}/cancel", headers=operator).status_code == 200
    assert api.post(f"/api/jobs/{other}/cancel", headers=operator).status_code == 403


@pytest.fixture
def programmer(make_key) -> str:
    """A programmer key on machine 1010 only."""
    return make_key(Role.PROGRAMMER, machines=["1010"], name="cell-1-cam")


def _library_programs(api, key: str) -> list[str]:
    return [p["path"] for p in api.get("/api/library/programs",
                                       headers={"X-Api-Key": key}).json()]


@pytest.mark.parametrize(("url", "as_key"), [
    ("/machines/{m}/api/files/local", "{k}"), ("/api/files/local?machineID={m}", "{k}"),
    ("/api/files/local", "{k}@{m}")])
def test_an_octoprint_upload_is_scoped_to_the_keys_machines_however_it_names_one(
        api, programmer, url: str, as_key: str) -> None:
    def upload(machine: str) -> Any:
        return api.post(url.format(m=machine), headers={
            "X-Api-Key": as_key.format(k=programmer, m=machine)}, data={"print": "true"},
            files={"file": ("PART1.MPF", b"G0 X1\nM30\n")})

    refused = upload("1011")
    taken = upload("1010")

    assert refused.status_code == 403 and "machine 1011" in refused.json()["statusMsg"]
    assert taken.status_code == 201, taken.text
    assert taken.json()["dncq"]["version"] == 1  # the refused upload kept nothing
    assert _library_programs(api, programmer) == [taken.json()["dncq"]["library"]]


@pytest.mark.parametrize("action", ["retry", "restore-replaced"])
def test_a_limited_programmer_may_not_retry_or_restore_another_machines_job(
        api, programmer, settings, action: str) -> None:
    other = _run_job(settings, "1011")

    answer = api.post(f"/api/jobs/{other}/{action}", headers={"X-Api-Key": programmer})

    assert answer.status_code == 403 and "machine 1011" in answer.json()["statusMsg"]


def test_a_refused_machine_id_is_named_with_its_control_characters_escaped(api,
                                                                        operator) -> None:
    answer = api.post("/api/cnc/sendFile", params={"machineID": "10\n11\x1b", "fileName": "O1"},
                      json=SEND, headers=operator)

    assert answer.status_code == 403
    assert answer.json()["statusMsg"] == ("you (key:cell-1) may not change machine "
                                          "'10\\n11\\x1b'; your machines: 1010")
