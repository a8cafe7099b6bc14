"""The API key: 401 without it, 403 when wrong, accepted as header or `apikey` query;
never shown back, and machine secrets masked."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator

import httpx
import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from jobs import db, models
from jobs.api.app import create_app
from jobs.settings import AuthMode, Settings
from tests.conftest import API_KEY
from tests.live_server import HTTP_TIMEOUT_S
from tests.servers import free_port, stop_process, wait_for_http
from worker import transports
from worker.transports.mock import MockOptions, MockTransport

KEYED_PATHS = ["/api/cnc/readProgramList?machineID=sim", "/api/machines"]
PATHS = [*KEYED_PATHS, "/api/health"]
PASSWORD = "hunter2-very-secret"


@pytest.fixture
def anonymous(settings: Settings, add_machines) -> Iterator[TestClient]:
    """A client that sends no key unless told to."""
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.mark.parametrize("path", KEYED_PATHS)
def test_request_without_a_key_answers_401(anonymous, path):
    response = anonymous.get(path)

    assert response.status_code == 401
    assert response.json() == {"errorCode": 20401, "errorMsg": "API key is missing."}


def test_health_without_a_key_answers_that_the_api_is_alive_and_nothing_more(anonymous):
    response = anonymous.get("/api/health")

    assert response.status_code == 200
    assert response.json() == {"status": "ok"}


def test_health_with_the_key_reports_version_database_and_broker(anonymous):
    body = anonymous.get("/api/health", headers={"X-Api-Key": API_KEY}).json()

    assert {"version", "database", "broker", "status"} <= body.keys()
    assert body["database"] == "ok"


def test_health_with_the_key_names_the_limits_a_request_is_refused_over(settings):
    # A client checks a file against them before it sends it: dncq refuses a body over its
    # limit from its length, but only once the whole body has come in.
    small = settings.model_copy(update={"max_json_body_bytes": 2048})

    with TestClient(create_app(small)) as c:
        body = c.get("/api/health", headers={"X-Api-Key": API_KEY}).json()

    assert body["limits"] == {"maxJsonBodyBytes": 2048,
                              "maxStreamBodyBytes": settings.max_stream_body_bytes,
                              "maxSendFileBytes": settings.max_send_file_bytes,
                              "maxReceiveFileBytes": settings.max_receive_file_bytes}


def test_health_reports_everything_without_a_key_when_auth_is_off(settings):
    open_settings = settings.model_copy(update={"auth": AuthMode.NONE})

    with TestClient(create_app(open_settings)) as c:
        body = c.get("/api/health").json()

    assert body["database"] == "ok"


@pytest.mark.parametrize("path", PATHS)
def test_request_with_a_wrong_key_answers_403(anonymous, path):
    response = anonymous.get(path, headers={"X-Api-Key": "not-the-key"})

    assert response.status_code == 403
    assert response.json()["errorCode"] == 20403


def test_a_wrong_key_is_refused_saying_no_key_of_this_dncq_is_the_one_sent(anonymous):
    response = anonymous.get("/api/machines", headers={"X-Api-Key": "not-the-key"})

    assert response.json() == {
        "errorCode": 20403, "errorMsg": "API key is not valid.",
        "statusMsg": "the key sent is neither this dncq's admin key nor one of its named keys"}


@pytest.mark.parametrize("path", PATHS)
def test_key_in_the_x_api_key_header_is_accepted(anonymous, path):
    response = anonymous.get(path, headers={"X-Api-Key": API_KEY})

    assert response.status_code == 200


@pytest.mark.parametrize("path", PATHS)
def test_key_in_the_apikey_query_parameter_is_accepted(anonymous, path):
    separator = "&" if "?" in path else "?"

    response = anonymous.get(f"{path}{separator}apikey={API_KEY}")

    assert response.status_code == 200


@pytest.mark.parametrize("path", PATHS)
def test_key_as_a_bearer_token_is_accepted_as_octoprint_takes_it(anonymous, path):
    assert anonymous.get(path, headers={"Authorization": f"Bearer {API_KEY}"}
                         ).status_code == 200
    assert anonymous.get(path, headers={"Authorization": "Bearer not-the-key"}
                         ).status_code == 403


@pytest.mark.parametrize("path", PATHS)
def test_wrong_key_in_the_query_answers_403(anonymous, path):
    separator = "&" if "?" in path else "?"

    response = anonymous.get(f"{path}{separator}apikey=not-the-key")

    assert response.status_code == 403


@pytest.mark.parametrize("path", PATHS)
def test_no_key_is_needed_when_auth_is_off(settings, add_machines, path):
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    open_settings = settings.model_copy(update={"auth": AuthMode.NONE})

    with TestClient(create_app(open_settings)) as c:
        response = c.get(path)

    assert response.status_code == 200


def test_the_key_never_appears_in_a_response_body(anonymous):
    responses = [
        anonymous.get(path, headers={"X-Api-Key": API_KEY}) for path in PATHS
    ] + [
        anonymous.get("/api/machines/sim", headers={"X-Api-Key": API_KEY}),
        anonymous.get("/api/cnc/readProgramList?machineID=nope", headers={"X-Api-Key": API_KEY}),
        anonymous.get("/openapi.json"),
        anonymous.get("/api/machines"),
        anonymous.get(f"/api/machines?apikey={API_KEY}x"),
    ]

    assert [r for r in responses if API_KEY in r.text] == []


class LoginOptions(MockOptions):
    """A mock that needs a login, as an FTP or share transport does."""

    password: SecretStr | None = None


@pytest.fixture
def login_transport(monkeypatch) -> str:
    """A transport with a secret option, registered for this test only."""
    monkeypatch.setitem(transports.REGISTRY, "mock-login",
                        transports.TransportKind(MockTransport, LoginOptions))
    return "mock-login"


def test_machine_password_is_masked_in_machines_responses(client, login_transport):
    machine = {"id": "ftp1", "name": "Lathe", "model": "Mock", "transport": login_transport,
               "options": {"password": PASSWORD, "latency_ms": 0}}

    responses = [
        client.post("/api/machines", json=machine),
        client.get("/api/machines"),
        client.get("/api/machines/ftp1"),
        client.put("/api/machines/ftp1", json={**machine, "name": "Lathe 2"}),
    ]

    assert [r.status_code for r in responses] == [201, 200, 200, 200]
    shown = [responses[0].json(), responses[1].json()[0], responses[2].json(), responses[3].json()]
    assert [m["options"]["password"] for m in shown] == ["**********"] * 4
    assert [r for r in responses if PASSWORD in r.text] == []


def test_option_named_like_a_secret_is_masked_whatever_its_transport(client, settings):
    # MockOptions has no such field; the row stands for one written by a future transport.
    with db.session_scope(settings.resolved_database_url) as session:
        session.add(models.Machine(id="old", name="Old", model="Mock", transport="mock",
                                   options={"api_token": PASSWORD}, tags=[]))

    body = client.get("/api/machines/old").json()

    assert body["options"] == {"api_token": "**********"}


def _access_log(tmp_path, *queries: str) -> str:
    """The access log of the real `dncq api` process after a GET of /api/health + each query."""
    port = free_port()
    env = {**os.environ, "DNCQ_DATA_DIR": str(tmp_path), "DNCQ_API_KEY": API_KEY,
           "DNCQ_PORT": str(port), "DNCQ_HOST": "127.0.0.1"}
    env.pop("DNCQ_AUTH", None)
    log_path = tmp_path / "api.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "jobs.cli", "api"], env=env,
                                stdout=log, stderr=subprocess.STDOUT)
    try:
        base = f"http://127.0.0.1:{port}/api/health"
        wait_for_http(lambda: httpx.get(base, headers={"X-Api-Key": API_KEY}), timeout_s=30)
        for query in queries:
            httpx.get(f"{base}?{query}", timeout=HTTP_TIMEOUT_S)
    finally:
        stop_process(proc)
    return log_path.read_text()


def test_a_key_in_the_query_is_masked_in_the_access_log(tmp_path):
    # The real `dncq api` process, with uvicorn's own access log.
    logged = _access_log(tmp_path, f"apikey={API_KEY}", "x=1&apikey=wrong-key-typed&y=2")

    assert "/api/health?apikey=***" in logged and "&apikey=***&y=2" in logged
    assert API_KEY not in logged and "wrong-key-typed" not in logged


def test_a_key_under_an_encoded_parameter_name_authenticates_and_is_masked_in_the_log(
        tmp_path, anonymous):
    # The name is decoded before the key is looked for: this is a login.
    assert anonymous.get(f"/api/health?api%6Bey={API_KEY}").status_code == 200

    logged = _access_log(tmp_path, f"api%6Bey={API_KEY}", "API%4bEY=wrong-key-typed")

    assert "/api/health?api%6Bey=***" in logged and "API%4bEY=***" in logged
    assert API_KEY not in logged and "wrong-key-typed" not in logged


def test_the_configured_key_under_any_parameter_name_is_masked_in_the_log(tmp_path):
    logged = _access_log(tmp_path, f"note={API_KEY}", f"q={API_KEY[:4]}%2D{API_KEY[5:]}")

    assert "/api/health?note=***" in logged and "/api/health?q=***" in logged
    assert API_KEY not in logged and f"{API_KEY[:4]}%2D{API_KEY[5:]}" not in logged
