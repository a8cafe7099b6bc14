"""Every API route declares the role it needs (a new route without one fails here); a key of
the role just below is refused with 403 and words that say why, a key of the role passes."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.routing import iter_route_contexts

from jobs.api.app import create_app
from jobs.api.deps import role_checks
from jobs.auth.roles import Role

OPEN_OPERATIONS = {("/api/health", "get")}  # liveness for load balancers: no key
OPEN_PATHS = {"/api/health", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"}
BELOW = {Role.OPERATOR: Role.VIEWER, Role.PROGRAMMER: Role.OPERATOR, Role.ADMIN: Role.PROGRAMMER}

# The policy of docs/api.md ("Roles"), route by route for a sample of each kind.
POLICY = [
    ("get", "/api/cnc/readProgramList", Role.VIEWER),
    ("get", "/api/cnc/receiveFile", Role.VIEWER),
    ("post", "/api/cnc/backupFiles", Role.VIEWER),
    ("post", "/api/cnc/sendFile", Role.OPERATOR),
    ("post", "/api/cnc/sendFileStream", Role.OPERATOR),
    ("get", "/api/cnc/deleteFile", Role.OPERATOR),
    ("get", "/api/cnc/lockFileByRange", Role.OPERATOR),
    ("get", "/api/cnc/selectProgram", Role.OPERATOR),
    ("post", "/api/cnc/batchSendFile", Role.OPERATOR),
    ("post", "/api/cnc/batchDeleteFile", Role.OPERATOR),
    ("post", "/api/jobs/{job_id}/stop", Role.OPERATOR),
    ("post", "/api/programs", Role.OPERATOR),
    ("get", "/api/jobs", Role.VIEWER),
    ("post", "/api/jobs/{job_id}/retry", Role.PROGRAMMER),
    ("post", "/api/library/approve/{path}", Role.PROGRAMMER),
    ("post", "/api/library/programs", Role.PROGRAMMER),
    ("post", "/api/inbox/{item_id}/approve", Role.PROGRAMMER),
    ("post", "/api/inbox/{item_id}/reject", Role.PROGRAMMER),
    ("get", "/api/machines", Role.VIEWER),
    ("put", "/api/machines/{machine_id}", Role.ADMIN),
    ("put", "/api/machines/{machine_id}/requests", Role.ADMIN),
    ("post", "/api/schedules", Role.ADMIN),
    ("get", "/api/schedules", Role.VIEWER),
    ("get", "/api/users", Role.ADMIN),
    ("post", "/api/keys", Role.ADMIN),
    ("get", "/api/audit", Role.ADMIN),
    ("get", "/api/lockouts", Role.ADMIN),
    ("delete", "/api/lockouts/{address}", Role.ADMIN),
    ("get", "/api/audit.csv", Role.ADMIN),
]


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    from jobs.settings import AuthMode, Settings

    return create_app(Settings(data_dir=tmp_path_factory.mktemp("data"),
                               api_key="a-key-0123456789", auth=AuthMode.KEY))


def test_every_operation_in_the_openapi_document_says_its_role(app) -> None:
    document = app.openapi()

    without = [(path, method) for path, operations in document["paths"].items()
               for method, operation in operations.items()
               if "x-dncq-role" not in operation and (path, method) not in OPEN_OPERATIONS]

    assert without == []


def test_every_served_route_declares_a_role_also_those_left_out_of_the_document(app) -> None:
    without = [(sorted(r.methods or ()), r.path_format) for r in iter_route_contexts(app.routes)
               if r.path_format and r.methods and r.path_format not in OPEN_PATHS
               and not role_checks(r)]

    assert without == []


def test_a_route_of_the_schema_without_a_role_would_be_caught(app) -> None:
    # The check above reads dependencies: a route made without `requires` has none.
    from fastapi import FastAPI

    bare = FastAPI()

    @bare.get("/api/new")
    def new() -> dict[str, Any]:
        return {}

    assert [r for r in iter_route_contexts(bare.routes) if r.path_format == "/api/new"
            and not role_checks(r)]


@pytest.mark.parametrize(("method", "path", "role"), POLICY,
                         ids=[f"{m} {p}" for m, p, _ in POLICY])
def test_the_route_needs_the_role_of_the_policy(app, method, path, role) -> None:
    assert app.openapi()["paths"][path][method]["x-dncq-role"] == role.value


def test_the_health_check_needs_no_key(app) -> None:
    assert "x-dncq-role" not in app.openapi()["paths"]["/api/health"]["get"]


def test_the_contracts_machine_writes_are_scoped_to_an_operators_machines(app) -> None:
    paths = app.openapi()["paths"]

    assert paths["/api/cnc/sendFile"]["post"]["x-dncq-machine-scoped"] is True
    assert paths["/api/cnc/deleteFile"]["get"]["x-dncq-machine-scoped"] is True
    assert "x-dncq-machine-scoped" not in paths["/api/cnc/receiveFile"]["get"]


SEND = {"content": "%\nO1000\n%\n"}
# One request per role that its holder gets through (not 401/403) and the role below does not.
SAMPLES: list[tuple[Role, str, str, dict[str, Any]]] = [
    (Role.OPERATOR, "post", "/api/cnc/sendFile?machineID=1010&fileName=O1000", {"json": SEND}),
    (Role.OPERATOR, "get", "/api/cnc/createDir?machineID=1010&dirName=NEW", {}),
    (Role.OPERATOR, "post", "/api/jobs/nojob/stop", {}),
    (Role.PROGRAMMER, "post", "/api/jobs", {"json": {
        "kind": "send", "content": "%\nO1\n%\n", "dry_run": True,
        "targets": [{"machineID": "1010", "fileName": "O1"}]}}),
    (Role.PROGRAMMER, "post", "/api/jobs/nojob/retry", {}),
    (Role.PROGRAMMER, "post", "/api/inbox/1/reject", {}),
    (Role.PROGRAMMER, "post", "/api/library/approve/VIPROS/0010", {}),
    (Role.ADMIN, "put", "/api/machines/1012", {"json": {
        "id": "1012", "name": "New", "model": "Mock"}}),
    (Role.ADMIN, "delete", "/api/schedules/nightly", {}),
    (Role.ADMIN, "get", "/api/users", {}),
    (Role.ADMIN, "get", "/api/audit", {}),
    (Role.ADMIN, "get", "/api/lockouts", {}),
    (Role.ADMIN, "delete", "/api/lockouts/10.0.0.7", {}),
    (Role.ADMIN, "post", "/api/keys", {"json": {"name": "made", "role": "viewer"}}),
]
IDS = [f"{r.value}: {m} {p.split('?')[0]}" for r, m, p, _ in SAMPLES]


@pytest.mark.parametrize(("role", "method", "path", "kwargs"), SAMPLES, ids=IDS)
def test_a_key_of_the_role_below_is_refused_with_403_saying_why(
        api, keys, role, method, path, kwargs) -> None:
    below = BELOW[role]

    answer = api.request(method, path, headers={"X-Api-Key": keys[below]}, **kwargs)

    assert answer.status_code == 403
    body = answer.json()
    assert body["errorCode"] == 20406
    assert f"needs the {role.value} role; you (key:{below.value}-" in body["statusMsg"]
    assert f"are {below.with_article}" in body["statusMsg"]


@pytest.mark.parametrize(("role", "method", "path", "kwargs"), SAMPLES, ids=IDS)
def test_a_key_of_the_role_gets_through(api, keys, role, method, path, kwargs) -> None:
    answer = api.request(method, path, headers={"X-Api-Key": keys[role]}, **kwargs)

    assert answer.status_code not in (401, 403), answer.text


@pytest.mark.parametrize("role", list(Role))
def test_a_viewer_key_reads(api, keys, role) -> None:
    assert api.get("/api/machines", headers={"X-Api-Key": keys[role]}).status_code == 200


def test_a_viewer_key_is_refused_every_machine_write_of_the_contract(api, keys) -> None:
    viewer = {"X-Api-Key": keys[Role.VIEWER]}
    writes = [api.post("/api/cnc/sendFile?machineID=1010&fileName=O1", json=SEND,
                       headers=viewer),
              api.get("/api/cnc/deleteFile?machineID=1010&fileName=O1", headers=viewer),
              api.get("/api/cnc/deleteDir?machineID=1010&dirName=D", headers=viewer),
              api.post("/api/cnc/batchDeleteFile", json=[{"machineID": "1010",
                                                          "fileName": "O1"}], headers=viewer)]

    assert [w.status_code for w in writes] == [403] * 4


# A job of each kind that needs more than an operator, as POST /api/jobs takes it.
PROGRAMMER_JOBS: list[dict[str, Any]] = [
    {"kind": "send", "content": "%\nO1\n%\n", "targets": [{"machineID": "1010",
                                                          "fileName": "O1"}]},
    {"kind": "delete", "targets": [{"machineID": "1010", "fileName": "O1"}]},
    {"kind": "backup", "machines": {"ids": ["1010"]}},
]


@pytest.mark.parametrize("job", PROGRAMMER_JOBS, ids=[j["kind"] for j in PROGRAMMER_JOBS])
def test_an_operator_key_is_refused_a_job_naming_the_role_its_kind_needs(
        api, keys, job) -> None:
    answer = api.post("/api/jobs", json=job, headers={"X-Api-Key": keys[Role.OPERATOR]})

    assert (answer.status_code, answer.json()["errorCode"]) == (403, 20406)
    assert answer.json()["statusMsg"].startswith(
        f"a {job['kind']} job needs the programmer role; you (key:operator-")


@pytest.mark.parametrize("kind", ["dnc_run", "send"])
def test_a_viewer_key_is_refused_a_job_of_any_kind_naming_the_operator_role(
        api, keys, kind) -> None:
    job = {"kind": kind, "program": "x.nc", "targets": [{"machineID": "1010"}]}

    answer = api.post("/api/jobs", json=job, headers={"X-Api-Key": keys[Role.VIEWER]})

    assert (answer.status_code, answer.json()["errorCode"]) == (403, 20406)
    assert answer.json()["statusMsg"].startswith(
        "a job of any kind needs the operator role; you (key:viewer-")


def test_a_viewer_key_is_refused_a_cancel_naming_the_role_the_jobs_kind_needs(
        api, keys) -> None:
    job = api.post("/api/jobs", json=PROGRAMMER_JOBS[1],
                   headers={"X-Api-Key": keys[Role.PROGRAMMER]}).json()

    answer = api.post(f"/api/jobs/{job['id']}/cancel", headers={"X-Api-Key": keys[Role.VIEWER]})

    assert (answer.status_code, answer.json()["errorCode"]) == (403, 20406)
    assert answer.json()["statusMsg"].startswith(
        "cancelling a delete job needs the programmer role; you (key:viewer-")


def test_an_operator_key_cancels_a_restore_it_may_start(api, keys, settings) -> None:
    from jobs import db
    from jobs.models import Job, JobKind

    with db.session_scope(settings.resolved_database_url) as session:  # as a restore makes it
        session.add(Job(id="restore1", kind=JobKind.RESTORE))

    answer = api.post("/api/jobs/restore1/cancel", headers={"X-Api-Key": keys[Role.OPERATOR]})

    assert answer.status_code == 200, answer.text


CONTRACT_CALLS: list[tuple[str, str, dict[str, Any]]] = [
    ("get", "/api/cnc/readProgramList?machineID=1010", {}),
    ("get", "/api/cnc/receiveFile?machineID=1010&fileName=O1000", {}),
    ("get", "/api/cnc/receiveFileStream?machineID=1010&fileName=O1000", {}),
    ("get", "/api/cnc/readCurrentProgram?machineID=1010", {}),
    ("post", "/api/cnc/sendFile?machineID=1010&fileName=O1000", {"json": SEND}),
    ("post", "/api/cnc/sendFileStream?machineID=1010&fileName=O1001",
     {"content": b"%\nO1001\n%\n"}),
    ("get", "/api/cnc/readAllPrograms?machineID=1010", {}),
    ("get", "/api/cnc/searchFile?machineID=1010&fileName=O1000", {}),
    ("get", "/api/cnc/selectProgram?machineID=1010&fileName=O1000", {}),
    ("get", "/api/cnc/lockFileByRange?machineID=1010&isLock=true&lockStart=1&lockEnd=2", {}),
    ("get", "/api/cnc/createDir?machineID=1010&dirName=NEW", {}),
    ("get", "/api/cnc/deleteDir?machineID=1010&dirName=NEW", {}),
    ("get", "/api/cnc/deleteFile?machineID=1010&fileName=O1001", {}),
    ("post", "/api/cnc/backupFiles", {"json": [{"machineID": "1010"}]}),
    ("post", "/api/cnc/batchDeleteFile", {"json": [{"machineID": "1010",
                                                     "fileName": "O1000"}]}),
    ("post", "/api/cnc/batchSendFile", {"json": {**SEND, "targets": [
        {"machineID": "1010", "fileName": "O1002"}]}}),
]


def test_the_admin_key_still_works_on_every_contract_route(api, settings) -> None:
    from tests.conftest import API_KEY

    answers = [api.request(m, p, headers={"X-Api-Key": API_KEY}, **kw)
               for m, p, kw in CONTRACT_CALLS]

    assert [(p, a.status_code) for (_, p, _), a in zip(CONTRACT_CALLS, answers, strict=True)
            if a.status_code in (401, 403) or a.status_code >= 500] == []
    document = create_app(settings).openapi()
    contract = {p for p in document["paths"] if p.startswith("/api/cnc/")}
    assert contract == {p.split("?")[0] for _, p, _ in CONTRACT_CALLS}


def test_an_operator_starts_and_cancels_drip_feed_runs_and_restores_and_nothing_else() -> None:
    # Read by the kind's value: a kind renamed must not quietly become a programmer's.
    from jobs.auth.roles import role_for_job
    from jobs.models import JobKind

    assert {k for k in JobKind if role_for_job(k) is Role.OPERATOR} \
        == {JobKind.DNC_RUN, JobKind.RESTORE}
    assert {role_for_job(k) for k in JobKind} == {Role.OPERATOR, Role.PROGRAMMER}
