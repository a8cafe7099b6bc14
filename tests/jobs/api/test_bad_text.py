"""Text that is not Unicode is refused at the edge with 400/20001; no stored record breaks a read.

A lone surrogate reaches the API as a JSON escape (`"\\ud800"`) in a body, or as bytes that
are not UTF-8 (`%ED%A0%80`, a surrogate written as UTF-8 would be; `%FF`) in a URL.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from jobs import db, service
from jobs.api.app import create_app
from jobs.backup_models import Schedule
from jobs.models import Job, JobKind, Machine
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.helpers import mock_file, on_machine, wait_done

BAD_PARAMETER = 20001
LONE = "\\ud800"  # as JSON writes it: one high surrogate with no low one after it
JSON_HEADERS = {"Content-Type": "application/json"}

BODIES = [
    ("/api/cnc/sendFile?machineID=sim&fileName=P", '{"content": "%s"}'),
    ("/api/cnc/batchSendFile", '{"content": "x", "targets": [{"machineID": "%s", '
                               '"fileName": "P"}]}'),
    ("/api/cnc/batchSendFile", '{"content": "x", "targets": [{"machineID": "sim", '
                               '"fileName": "%s"}]}'),
    ("/api/cnc/batchSendFile", '{"content": "x", "targets": [{"machineID": "sim", '
                               '"fileName": "P", "DirAtCNC": "%s"}]}'),
    ("/api/cnc/batchDeleteFile", '[{"machineID": "sim", "fileName": "P", "dirAtCNC": "%s"}]'),
    ("/api/cnc/batchDeleteFile", '[{"machineID": "sim", "fileName": "P", "subDir": "%s"}]'),
    ("/api/cnc/backupFiles", '[{"machineID": "sim", "dirAtCNC": "%s"}]'),
    ("/api/jobs", '{"kind": "delete", "targets": [{"machineID": "sim", "fileName": "P"}], '
                  '"created_by": "%s"}'),
    ("/api/jobs", '{"kind": "delete", "machines": {"tags": ["%s"]}, "fileName": "P"}'),
    ("/api/jobs", '{"kind": "send", "content": "x", "targets": [{"machineID": "sim", '
                  '"fileName": "P%s"}]}'),
    ("/api/machines", '{"id": "%s", "name": "N", "model": "Mock"}'),
    ("/api/machines", '{"id": "m2", "name": "N", "model": "Mock", "tags": ["%s"]}'),
    ("/api/machines", '{"id": "m2", "name": "N", "model": "Mock", "options": {"folder": "%s"}}'),
    ("/api/schedules", '{"name": "s", "cron": "0 2 * * *", "dirAtCNC": "%s"}'),
    ("/api/schedules", '{"name": "s", "cron": "0 2 * * *", "machines": {"tags": ["%s"]}}'),
    ("/api/schedules", '{"name": "s", "cron": "0 2 * * *", "%s": 1}'),
]

QUERIES = [
    ("GET", "/api/cnc/readProgramList?machineID=sim&dirAtCNC=%s"),
    ("GET", "/api/cnc/readProgramList?machineID=sim&subDir=%s"),
    ("GET", "/api/cnc/receiveFile?machineID=sim&fileName=%s"),
    ("GET", "/api/cnc/deleteFile?machineID=sim&fileName=%s"),
    ("GET", "/api/cnc/createDir?machineID=sim&dirName=%s"),
    ("GET", "/api/cnc/readProgramList?machineID=%s"),
    ("POST", "/api/cnc/sendFileStream?machineID=sim&fileName=%s"),
    ("POST", "/api/cnc/batchDeleteFile?force=%s"),
    ("GET", "/api/machines?tag=%s"),
    ("GET", "/api/machines/%s"),
    ("GET", "/api/jobs?machine=%s"),
    ("GET", "/api/jobs/%s"),
    ("POST", "/api/schedules/%s/run"),
    ("DELETE", "/api/schedules/%s"),
    ("GET", "/api/backups?job=%s"),
]
NOT_UTF8 = ["%ED%A0%80", "%FF"]


@pytest.fixture
def sim(add_machines: Callable[..., Any], client: TestClient) -> None:
    """A mock machine `sim` holding the program P."""
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    sent = client.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": "P"},
                       json={"content": "G0\n"})
    assert sent.json()["errorCode"] == 0


def _refused(response: Any) -> None:
    assert response.status_code == 400, response.text
    body = response.json()
    assert body["errorCode"] == BAD_PARAMETER
    assert "Unicode" in body["statusMsg"] or "UTF-8" in body["statusMsg"]


@pytest.mark.parametrize(("path", "body"), BODIES, ids=[f"{p} {b}" for p, b in BODIES])
def test_lone_surrogate_in_a_json_body_answers_400_and_records_nothing(
        client, settings, sim, path, body):
    _refused(client.post(path, content=(body % LONE).encode(), headers=JSON_HEADERS))

    with db.session_scope(settings.resolved_database_url) as session:
        assert session.query(Job).count() == 0
        assert session.query(Schedule).count() == 0
        assert [m.id for m in session.query(Machine)] == ["sim"]


def test_batch_delete_with_a_lone_surrogate_folder_deletes_nothing(client, sim):
    body = '[{"machineID": "sim", "fileName": "P", "dirAtCNC": "LONE"}]'.replace("LONE", LONE)
    _refused(client.post("/api/cnc/batchDeleteFile", content=body.encode(),
                         headers=JSON_HEADERS))

    listing = client.get("/api/cnc/readProgramList", params={"machineID": "sim"}).json()
    assert listing["programs"] == ["P"]


def test_lone_surrogate_paired_properly_is_text_and_accepted(client, sim):
    body = '{"content": "\\ud83d\\ude00"}'  # U+1F600 written as a surrogate pair
    response = client.post("/api/cnc/sendFile?machineID=sim&fileName=SMILE",
                           content=body.encode(), headers=JSON_HEADERS)

    assert response.json() == {"errorCode": 0, "errorMsg": "Success"}


@pytest.mark.parametrize("raw", NOT_UTF8)
@pytest.mark.parametrize(("method", "url"), QUERIES, ids=[u for _, u in QUERIES])
def test_url_that_is_not_utf8_answers_400(client, sim, method, url, raw):
    _refused(client.request(method, url % raw, content=b"[]", headers=JSON_HEADERS))


def test_url_with_real_non_ascii_text_is_accepted(client, sim):
    response = client.get("/api/cnc/readProgramList?machineID=sim&subDir=%C3%A9t%C3%A9")

    assert response.json()["errorCode"] == 158  # a name that is text: looked for, not there


def test_every_route_of_the_api_refuses_a_query_that_is_not_utf8(client):
    paths = client.get("/openapi.json").json()["paths"]
    answers = {}
    for template, operations in paths.items():
        path = re.sub(r"\{[^}]+\}", "x", template)
        for method in operations:
            answers[f"{method} {template}"] = client.request(method, f"{path}?q=%FF").status_code

    assert len(answers) > 30
    assert {op: status for op, status in answers.items() if status != 400} == {}


# -- records made before the edge check: every read still answers ------------------


@pytest.fixture
def unicode_less_records(settings: Settings, sim: None) -> str:
    """A job, a machine and a schedule whose JSON fields hold a lone surrogate, as a
    database written before the edge refused them holds; returns the job id."""
    with db.session_scope(settings.resolved_database_url) as session:
        job = service.create(session=session, kind=JobKind.DELETE, targets=[
            service.TargetIn(machineID="sim", fileName="P")])
        job.options = {"note": "\udc80"}
        job.targets[0].params = {"fileName": "P", "dirAtCNC": "\ud800"}
        machine = session.get(Machine, "sim")
        assert machine is not None
        machine.tags = ["\ud800"]
        machine.options = {"folder": "\udfff"}
        session.add(Schedule(name="s", cron="0 2 * * *", timezone="UTC",
                             machines={"tags": ["\ud800"]}, retention="", notify=[]))
        return job.id


@pytest.mark.parametrize("path", ["/api/jobs/{job}", "/api/jobs", "/api/machines",
                                  "/api/machines/sim", "/api/schedules", "/api/schedules/s"])
def test_stored_text_that_is_not_unicode_never_fails_a_read(settings, unicode_less_records,
                                                            path):
    with TestClient(create_app(settings), headers={"X-Api-Key": API_KEY},
                    raise_server_exceptions=False) as client:
        response = client.get(path.format(job=unicode_less_records))

    assert response.status_code == 200, response.text
    assert "\ufffd" in response.text


def test_job_with_a_stored_lone_surrogate_shows_it_as_a_replacement_character(
        client, unicode_less_records):
    job = client.get(f"/api/jobs/{unicode_less_records}").json()

    assert job["targets"][0]["dirAtCNC"] == "\ufffd"


def test_stored_delete_target_with_a_lone_surrogate_fails_20001_and_deletes_nothing(
        queue_client, queue_settings, add_machines):
    # A target recorded before the edge check: its worker must record a failure, not lose
    # the result (which a retry then took for "already deleted": a false success).
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    mock_file(queue_settings, "sim", "P", "G0\n")
    with db.session_scope(queue_settings.resolved_database_url) as session:
        job = service.create(session=session, kind=JobKind.DELETE, targets=[
            service.TargetIn(machineID="sim", fileName="P")])
        job.targets[0].params = {"fileName": "P", "dirAtCNC": "\ud800"}
        job_id = job.id
    service.dispatch(settings=queue_settings, job_id=job_id)

    target = wait_done(queue_client, job_id)["targets"][0]

    assert (target["state"], target["errorCode"]) == ("failed", BAD_PARAMETER)
    assert on_machine(queue_settings, "sim", "P").read_text() == "G0\n"


def test_the_api_doc_quotes_the_refusals_as_the_server_words_them(client, sim):
    doc = " ".join((Path(__file__).resolve().parents[3] / "docs" / "api.md").read_text().split())
    query = client.get("/api/cnc/readProgramList?machineID=sim&subDir=%FF").json()
    body = client.post("/api/cnc/sendFile?machineID=sim&fileName=P",
                       content=b'{"content": "\\ud800"}', headers=JSON_HEADERS).json()

    assert query["statusMsg"] == "subDir: not valid UTF-8"
    assert '"statusMsg": "<where>: not valid UTF-8"' in doc
    assert f"`{body['statusMsg']}`" in doc
