"""The audit trail: each state-changing request recorded once answered, with the principal,
its address, the action and target; reads are not; no secret is kept; filters and CSV."""

from __future__ import annotations

import csv
import io
from datetime import UTC, datetime, timedelta

import httpx
from fastapi.testclient import TestClient

from jobs import db
from jobs.api.app import create_app
from jobs.auth import audit
from jobs.auth.roles import Principal, Role
from tests.conftest import API_KEY
from tests.live_server import HTTP_TIMEOUT_S, serving

ADMIN = {"X-Api-Key": API_KEY}
SEND = {"content": "%\nO1000\n%\n"}
MACHINE = {"id": "1012", "name": "New", "model": "Mock"}


def _events(api, **params):
    return api.get("/api/audit", headers=ADMIN, params=params).json()


def test_a_fleet_change_by_the_admin_key_is_recorded_with_who_what_and_where(api) -> None:
    api.put("/api/machines/1012", json=MACHINE, headers=ADMIN)

    [event] = _events(api)
    assert {k: event[k] for k in ("who", "kind", "role", "address", "method", "path",
                                  "status", "action", "target")} == {
        "who": "admin-key", "kind": "admin-key", "role": "admin", "address": "testclient",
        "method": "PUT", "path": "/api/machines/1012", "status": 200,
        "action": "machines.put", "target": "1012"}


def test_a_request_refused_for_a_nul_in_its_path_or_query_is_recorded_on_every_database(
        settings, database_url) -> None:
    # PostgreSQL stores no NUL: written as it came, the refusal went unrecorded there.
    on = settings.model_copy(update={"database_url": database_url})
    with TestClient(create_app(on), headers=ADMIN) as api:
        api.put("/api/machines/10%0012", json=MACHINE)
        api.get("/api/cnc/deleteFile", params={"machineID": "1012", "fileName": "A\x00.nc"})

        events = _events(api)
    assert [(e["path"], e["target"]) for e in events] == [
        ("/api/cnc/deleteFile", "1012"), ("/api/machines/10\\x0012", "10\\x0012")]
    assert events[0]["detail"]["fileName"] == "A\\x00.nc"


def test_a_file_sent_with_a_named_key_names_the_key_the_machine_and_the_file(api,
                                                                           make_key) -> None:
    key = make_key(Role.OPERATOR, name="cell-1")

    api.post("/api/cnc/sendFile?machineID=1010&fileName=O1000", json=SEND,
             headers={"X-Api-Key": key})

    [event] = _events(api)
    assert (event["who"], event["kind"], event["role"], event["action"], event["target"],
            event["detail"]) == ("key:cell-1", "key", "operator", "cnc.sendFile", "1010",
                                 {"fileName": "O1000"})


def test_a_refused_request_is_recorded_with_its_403(api, make_key) -> None:
    key = make_key(Role.VIEWER, name="reader")

    api.post("/api/cnc/sendFile?machineID=1010&fileName=O1000", json=SEND,
             headers={"X-Api-Key": key})

    [event] = _events(api)
    assert (event["who"], event["status"]) == ("key:reader", 403)


def test_a_request_without_a_key_is_recorded_as_nobody(api) -> None:
    api.delete("/api/machines/1010")

    [event] = _events(api)
    assert (event["who"], event["kind"], event["status"], event["action"]) == (
        "-", "none", 401, "machines.delete")


def test_reads_are_not_recorded(api) -> None:
    api.get("/api/machines", headers=ADMIN)
    api.get("/api/cnc/readProgramList?machineID=1010", headers=ADMIN)

    assert _events(api) == []


def test_the_contracts_gets_that_change_a_machine_are_recorded(api) -> None:
    api.get("/api/cnc/createDir?machineID=1010&dirName=NEW", headers=ADMIN)

    [event] = _events(api)
    assert (event["method"], event["action"], event["target"], event["detail"]) == (
        "GET", "cnc.createDir", "1010", {"dirName": "NEW"})


def test_a_job_submitted_is_recorded_with_its_job_id(api) -> None:
    job = api.post("/api/jobs", headers=ADMIN, json={
        "kind": "send", "content": "%\nO1\n%\n",
        "targets": [{"machineID": "1010", "fileName": "O1"}]}).json()

    [event] = _events(api)
    assert (event["action"], event["target"], event["status"]) == ("jobs.create", job["id"],
                                                                    202)


def test_a_users_password_and_a_key_in_the_query_are_never_recorded(api) -> None:
    api.post("/api/users", headers=ADMIN, json={"name": "alice", "password": "s3cret-pass!",
                                                "role": "viewer"})
    api.patch("/api/users/alice", headers=ADMIN, json={"password": "n3w-s3cret-pass"})
    api.put(f"/api/machines/1012?apikey={API_KEY}", json=MACHINE)

    events = api.get("/api/audit", headers=ADMIN)
    exported = api.get("/api/audit.csv", headers=ADMIN)

    assert [e["action"] for e in events.json()] == ["machines.put", "users.set", "users.add"]
    for text in (events.text, exported.text):
        assert "s3cret-pass" not in text and API_KEY not in text


def test_the_principal_the_dashboard_put_on_the_request_is_used_and_recorded(settings,
                                                                           add_machines):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})
    app = create_app(settings)
    alice = Principal(name="alice", kind="user", role=Role.PROGRAMMER)

    with TestClient(_wrapped(app, alice)) as c:
        answered = c.post("/api/library/approve/VIPROS/0010")
        refused = c.put("/api/machines/1012", json=MACHINE)
    with db.session_scope(settings.resolved_database_url) as session:
        events = audit.list_events(session=session)

    assert answered.status_code == 404 and refused.status_code == 403
    assert "you (alice) are a programmer" in refused.json()["statusMsg"]
    assert [(e.who, e.kind, e.action) for e in events] == [
        ("alice", "user", "machines.put"), ("alice", "user", "library.approve")]


def _wrapped(app, principal):
    """The app behind a stand-in for the dashboard's session middleware."""

    async def asgi(scope, receive, send):
        if scope["type"] == "http":
            scope.setdefault("state", {})["principal"] = principal
        await app(scope, receive, send)

    return asgi


def test_the_address_is_the_clients_on_a_real_server(settings, add_machines) -> None:
    with serving(create_app(settings)) as server:
        httpx.put(f"{server.url}/api/machines/1012", json=MACHINE, headers=ADMIN,
                  timeout=HTTP_TIMEOUT_S)
        server.wait_idle()
        events = httpx.get(f"{server.url}/api/audit", headers=ADMIN,
                           timeout=HTTP_TIMEOUT_S).json()

    assert [(e["address"], e["action"]) for e in events] == [("127.0.0.1", "machines.put")]


def test_events_are_filtered_by_who_action_group_and_time(api, make_key) -> None:
    key = make_key(Role.ADMIN, name="ops")
    api.put("/api/machines/1012", json=MACHINE, headers=ADMIN)
    api.delete("/api/machines/1012", headers={"X-Api-Key": key})
    api.post("/api/schedules/prune", headers={"X-Api-Key": key})
    now = datetime.now(UTC)

    assert [e["action"] for e in _events(api, who="key:ops")] == ["schedules.prune",
                                                                  "machines.delete"]
    assert [e["who"] for e in _events(api, action="machines")] == ["key:ops", "admin-key"]
    assert _events(api, since=(now + timedelta(seconds=1)).isoformat()) == []
    assert len(_events(api, until=(now + timedelta(seconds=1)).isoformat(), limit=2)) == 2


def test_the_csv_export_has_a_header_and_a_row_per_event(api) -> None:
    api.put("/api/machines/1012", json=MACHINE, headers=ADMIN)
    api.delete("/api/machines/1012", headers=ADMIN)

    exported = api.get("/api/audit.csv", headers=ADMIN)

    assert exported.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(exported.text)))
    assert [(r["who"], r["action"], r["target"], r["status"]) for r in rows] == [
        ("admin-key", "machines.delete", "1012", "204"),
        ("admin-key", "machines.put", "1012", "200")]


def test_a_cell_that_would_be_a_spreadsheet_formula_is_quoted(settings) -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        audit.record(session=session, principal=None, address=None, method="POST",
                     path="/api/x", status=200, action="x.y", target="=HYPERLINK(1)")
        found = audit.list_events(session=session)

    [_, row] = list(csv.reader(io.StringIO("".join(audit.as_csv(found)))))
    assert row[9] == "'=HYPERLINK(1)"
