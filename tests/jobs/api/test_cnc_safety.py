"""Bad input gets a clear error, and nothing is written outside a machine's roots.

After every refused write the data folder holds no new file or folder (the
machine's storage included) and no `.dncq-part-*` leftover.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from jobs import db
from jobs.api.app import create_app
from jobs.fleet import registry
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.live_server import HTTP_TIMEOUT_S, serving
from worker.transports.base import Dropped
from worker.transports.mock import PART_PREFIX, MockOptions, MockTransport

FLEET = [
    {"id": "sim", "name": "Sim", "model": "Mock"},
    {"id": "siemens", "name": "Mill", "model": "Siemens"},
    {"id": "tnc", "name": "TNC", "model": "Heidenhain TNC640"},
    {"id": "off", "name": "Off", "model": "Mock", "options": {"offline": True}},
    {"id": "run", "name": "Run", "model": "Mock", "options": {"current_program": "P1"}},
]
SENDS = ["sendFile", "sendFileStream"]
CONTENT = b"G0 X0 Y0\nM30\n"
# The database, the mocks' run-time state and the upload spool are dncq's own files.
OWN_FILES = ("dncq.sqlite3", "state.", "spool")

BAD_PARAMETER = 20001
PATH_OUTSIDE_ROOT = 20002


def _paths(data_dir: Path) -> set[str]:
    return {p.relative_to(data_dir).as_posix() for p in data_dir.rglob("*")
            if not p.name.startswith(OWN_FILES)}


@pytest.fixture
def fleet(add_machines: Callable[..., Any], client: TestClient) -> None:
    """The machines above, each opened once so that its storage roots exist."""
    add_machines(*FLEET)
    for entry in FLEET:
        client.get("/api/cnc/readProgramList", params={"machineID": entry["id"]})


@pytest.fixture
def assert_nothing_written(settings: Settings, fleet: None) -> Callable[[], None]:
    """Check that no file or folder appeared in the data folder since the test started."""
    before = _paths(settings.data_dir)

    def check() -> None:
        assert _paths(settings.data_dir) - before == set()
        assert not list(settings.data_dir.rglob(f"{PART_PREFIX}*"))

    return check


def send(client: TestClient, endpoint: str, params: dict[str, str],
         data: bytes = CONTENT) -> httpx.Response:
    """Send `data` through sendFile (JSON) or sendFileStream (raw body)."""
    if endpoint == "sendFile":
        return client.post("/api/cnc/sendFile", params=params, json={"content": data.decode()})
    return client.post("/api/cnc/sendFileStream", params=params, content=data)


def storage(settings: Settings, machine_id: str) -> Path:
    """The mock machine's storage folder."""
    return settings.data_dir / "mock" / machine_id / "files"


# -- paths that leave the root ---------------------------------------------------------

LEAVING_ROOT = [
    ("sim", {"dirAtCNC": ".."}),
    ("sim", {"dirAtCNC": "/../.."}),
    ("sim", {"dirAtCNC": "a/../../.."}),
    ("sim", {"subDir": "../x"}),
    ("sim", {"subDir": "a/../../x"}),
    ("sim", {"dirAtCNC": "..\\..\\x"}),
    ("sim", {"subDir": "..\\..\\x"}),
    ("siemens", {"dirAtCNC": "/etc"}),
    ("siemens", {"dirAtCNC": "/nckfs/../../etc"}),
    ("tnc", {"dirAtCNC": "C:\\"}),
    ("tnc", {"dirAtCNC": "C:\\Windows\\Temp"}),
    ("tnc", {"dirAtCNC": "TNC:\\..\\..\\x"}),
]


@pytest.mark.parametrize("endpoint", SENDS)
@pytest.mark.parametrize(("machine_id", "folder"), LEAVING_ROOT)
def test_send_refuses_a_folder_outside_the_machine_roots(
        client, assert_nothing_written, endpoint, machine_id, folder):
    body = send(client, endpoint, {"machineID": machine_id, "fileName": "PART.MPF", **folder})

    assert body.status_code == 200
    assert body.json()["errorCode"] == PATH_OUTSIDE_ROOT
    assert body.json()["statusMsg"]
    assert_nothing_written()


NOT_A_NAME = ["a/b.MPF", "a\\b.MPF", "../PART.MPF", "..\\PART.MPF", "..", "C:PART.MPF",
              "PART\x00.MPF", "A" * 256, f"{PART_PREFIX}x",
              "PART\ufffd.MPF"]  # what a query's %FF (not UTF-8) decodes to


@pytest.mark.parametrize("endpoint", SENDS)
@pytest.mark.parametrize("file_name", NOT_A_NAME, ids=lambda n: n if len(n) < 20 else "long")
def test_send_refuses_a_file_name_that_is_not_a_plain_name(
        client, assert_nothing_written, endpoint, file_name):
    body = send(client, endpoint, {"machineID": "sim", "fileName": file_name}).json()

    assert body["errorCode"] == BAD_PARAMETER
    assert body["statusMsg"]
    assert_nothing_written()


@pytest.mark.parametrize("folder", [{"dirAtCNC": "a\x00b"}, {"subDir": "a\x00b"},
                                    {"dirAtCNC": "d" * 256}, {"subDir": "d" * 256}])
def test_send_refuses_a_folder_with_a_nul_byte_or_an_over_long_name(
        client, assert_nothing_written, folder):
    body = send(client, "sendFile", {"machineID": "sim", "fileName": "P", **folder}).json()

    assert body["errorCode"] == BAD_PARAMETER
    assert_nothing_written()


def test_send_refuses_a_name_too_long_for_the_machine_storage_as_bad_parameter(
        client, assert_nothing_written):
    # 200 characters, 400 bytes in UTF-8: over what the mock's disk takes in one name.
    body = send(client, "sendFile", {"machineID": "sim", "fileName": "é" * 200}).json()

    assert body["errorCode"] == BAD_PARAMETER
    assert_nothing_written()


@pytest.mark.parametrize("dir_name", ["..", "../x", "a/b", "a\\b", "C:", "x\x00", "d" * 256],
                         ids=lambda n: n if len(n) < 20 else "long")
def test_create_dir_refuses_a_dir_name_that_is_not_a_plain_name(
        client, assert_nothing_written, dir_name):
    body = client.get("/api/cnc/createDir", params={"machineID": "sim", "dirName": dir_name})

    assert body.json()["errorCode"] == BAD_PARAMETER
    assert_nothing_written()


@pytest.mark.parametrize(("machine_id", "folder"), LEAVING_ROOT)
def test_create_dir_refuses_a_folder_outside_the_machine_roots(
        client, assert_nothing_written, machine_id, folder):
    params = {"machineID": machine_id, "dirName": "new", **folder}
    body = client.get("/api/cnc/createDir", params=params).json()

    assert body["errorCode"] == PATH_OUTSIDE_ROOT
    assert_nothing_written()


@pytest.mark.parametrize("folder", ["..", "../..", "/../..", "..\\.."])
def test_delete_file_cannot_reach_a_file_beside_the_machine_storage(
        client, settings, fleet, folder):
    decoys = [settings.data_dir / "mock" / "sim" / "VICTIM", settings.data_dir / "VICTIM"]
    for decoy in decoys:
        decoy.write_bytes(b"keep me")
    params = {"machineID": "sim", "fileName": "VICTIM", "dirAtCNC": folder}

    body = client.get("/api/cnc/deleteFile", params=params).json()

    assert body["errorCode"] == PATH_OUTSIDE_ROOT
    assert all(decoy.read_bytes() == b"keep me" for decoy in decoys)


def test_read_program_list_refuses_a_folder_outside_the_model_roots(client, fleet):
    body = client.get("/api/cnc/readProgramList",
                      params={"machineID": "siemens", "dirAtCNC": "/etc"}).json()

    assert body["errorCode"] == PATH_OUTSIDE_ROOT
    assert "programs" not in body


def test_absolute_path_on_a_mock_machine_stays_inside_its_storage(client, fleet):
    params = {"machineID": "sim", "dirAtCNC": "/etc", "fileName": "passwd"}

    body = client.get("/api/cnc/receiveFile", params=params).json()

    assert body["errorCode"] == 158


# -- the contract's own errors ------------------------------------------------------------


@pytest.mark.parametrize("endpoint", SENDS)
def test_send_to_an_unknown_machine_answers_10003_naming_it(client, assert_nothing_written,
                                                            endpoint):
    body = send(client, endpoint, {"machineID": "nope", "fileName": "P"}).json()

    assert body == {"errorCode": 10003, "errorMsg": "Machine ID does not exist.",
                    "statusMsg": "Invalid MachineID (nope)"}
    assert_nothing_written()


@pytest.mark.parametrize("endpoint", ["receiveFile", "receiveFileStream", "deleteFile"])
def test_missing_file_answers_158(client, fleet, endpoint):
    response = client.get(f"/api/cnc/{endpoint}", params={"machineID": "sim", "fileName": "NO"})

    assert response.status_code == 200
    assert response.json()["errorCode"] == 158
    assert response.json()["errorMsg"] == "Path is not found."


@pytest.mark.parametrize("endpoint", SENDS)
def test_send_over_an_existing_file_answers_142_and_keeps_the_old_file(
        client, settings, fleet, endpoint):
    assert send(client, endpoint, {"machineID": "sim", "fileName": "P"}).json()["errorCode"] == 0

    body = send(client, endpoint, {"machineID": "sim", "fileName": "P"}, b"other\n").json()

    assert body["errorCode"] == 142
    assert body["errorMsg"] == "Path exists."
    assert (storage(settings, "sim") / "P").read_bytes() == CONTENT
    assert not list(storage(settings, "sim").glob(f"{PART_PREFIX}*"))


# -- requests that cannot be parsed --------------------------------------------------------


@pytest.mark.parametrize(("method", "endpoint"), [
    ("GET", "readProgramList"), ("GET", "receiveFile"), ("POST", "sendFile"),
    ("POST", "sendFileStream"),
])
def test_missing_machine_id_answers_400_with_the_error_body(client, fleet, method, endpoint):
    kwargs: dict[str, Any] = {"json": {"content": "x"}} if endpoint == "sendFile" else {}
    response = client.request(method, f"/api/cnc/{endpoint}", params={"fileName": "P"}, **kwargs)

    assert response.status_code == 400
    assert response.json()["errorCode"] == BAD_PARAMETER
    assert "machineID" in response.json()["statusMsg"]


@pytest.mark.parametrize(("method", "endpoint"), [
    ("GET", "receiveFile"), ("GET", "receiveFileStream"), ("GET", "deleteFile"),
    ("POST", "sendFile"), ("POST", "sendFileStream"),
])
def test_missing_file_name_answers_400_with_the_error_body(client, assert_nothing_written,
                                                           method, endpoint):
    kwargs: dict[str, Any] = {"json": {"content": "x"}} if endpoint == "sendFile" else {}
    if endpoint == "sendFileStream":
        kwargs = {"content": CONTENT}
    response = client.request(method, f"/api/cnc/{endpoint}", params={"machineID": "sim"},
                              **kwargs)

    assert response.status_code == 400
    assert response.json() == {"errorCode": BAD_PARAMETER, "errorMsg": "Bad parameter.",
                               "statusMsg": "fileName is required"}
    assert_nothing_written()


def test_create_dir_without_dir_name_answers_400(client, assert_nothing_written):
    response = client.get("/api/cnc/createDir", params={"machineID": "sim"})

    assert response.status_code == 400
    assert response.json()["errorCode"] == BAD_PARAMETER
    assert_nothing_written()


@pytest.mark.parametrize("raw", [b"{bad", b'{"content": "x"', b"[1, 2]", b'{"content": 5}'])
def test_send_file_with_a_malformed_json_body_answers_400(client, assert_nothing_written, raw):
    response = client.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": "P"},
                           content=raw, headers={"Content-Type": "application/json"})

    assert response.status_code == 400
    assert response.json()["errorCode"] == BAD_PARAMETER
    assert_nothing_written()


def test_a_body_that_is_not_json_is_said_to_be_so_with_where_it_breaks_off(
        client, assert_nothing_written):
    response = client.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": "P"},
                           content=b'{"content": x}', headers={"Content-Type": "application/json"})

    assert response.status_code == 400
    assert response.json()["statusMsg"] == "body: JSON decode error at character 12"
    assert_nothing_written()


@pytest.mark.parametrize(("raw", "content_type"), [(b'{"content": "x"}', "text/plain"),
                                                   (b"", "application/json")])
def test_send_file_without_a_json_body_says_the_body_is_the_problem(
        client, assert_nothing_written, raw, content_type):
    response = client.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": "P"},
                           content=raw, headers={"Content-Type": content_type})

    assert response.status_code == 400
    assert response.json()["statusMsg"].startswith("body: ")
    assert_nothing_written()


# -- body limits ---------------------------------------------------------------------------

JSON_LIMIT = 1024
STREAM_LIMIT = 4096


@pytest.fixture
def small_client(settings: Settings, fleet: None) -> Iterator[TestClient]:
    """The API with small body limits."""
    small = settings.model_copy(update={"max_json_body_bytes": JSON_LIMIT,
                                        "max_stream_body_bytes": STREAM_LIMIT})
    with TestClient(create_app(small), headers={"X-Api-Key": API_KEY}) as c:
        yield c


def _over_limit(endpoint: str, chunked: bool) -> dict[str, Any]:
    if endpoint == "sendFile":
        raw = b'{"content": "' + b"x" * JSON_LIMIT + b'"}'
        headers = {"Content-Type": "application/json"}
    else:
        raw, headers = b"x" * (STREAM_LIMIT + 1), {}
    if chunked:  # no Content-Length: the limit must be counted while reading
        return {"content": iter([raw[i:i + 500] for i in range(0, len(raw), 500)]),
                "headers": headers}
    return {"content": raw, "headers": headers}


@pytest.mark.parametrize("chunked", [False, True], ids=["content-length", "chunked"])
@pytest.mark.parametrize("endpoint", SENDS)
def test_body_over_the_limit_answers_413_with_the_error_body(
        small_client, assert_nothing_written, endpoint, chunked):
    response = small_client.post(f"/api/cnc/{endpoint}",
                                 params={"machineID": "sim", "fileName": "BIG"},
                                 **_over_limit(endpoint, chunked))

    assert response.status_code == 413
    assert response.json()["errorCode"] == 20013
    assert response.json()["errorMsg"] == "Request body is too large."
    assert_nothing_written()


@pytest.mark.parametrize("chunked", [False, True], ids=["content-length", "chunked"])
def test_stream_body_of_exactly_the_limit_is_accepted(small_client, settings, chunked):
    raw = b"x" * STREAM_LIMIT
    content = iter([raw[:1000], raw[1000:]]) if chunked else raw
    response = small_client.post("/api/cnc/sendFileStream",
                                 params={"machineID": "sim", "fileName": "EXACT"},
                                 content=content)

    assert response.json()["errorCode"] == 0
    assert (storage(settings, "sim") / "EXACT").read_bytes() == raw


# -- machine state ---------------------------------------------------------------------------


@pytest.mark.parametrize(("method", "endpoint"), [
    ("GET", "readProgramList"), ("GET", "receiveFile"), ("GET", "deleteFile"),
    ("POST", "sendFile"), ("POST", "sendFileStream"),
])
def test_offline_mock_machine_answers_20004(client, assert_nothing_written, method, endpoint):
    kwargs: dict[str, Any] = {"json": {"content": "x"}} if endpoint == "sendFile" else {}
    response = client.request(method, f"/api/cnc/{endpoint}",
                              params={"machineID": "off", "fileName": "P"}, **kwargs)

    assert response.json()["errorCode"] == 20004
    assert response.json()["errorMsg"] == "Machine is offline."
    assert_nothing_written()


class Interrupted(Exception):
    """The uploading client gave up midway."""


def test_send_file_stream_interrupted_by_the_client_leaves_no_file(settings, fleet, caplog):
    def body() -> Iterator[bytes]:
        yield b"x" * 256 * 1024
        yield b"y" * 256 * 1024
        raise Interrupted

    with serving(create_app(settings)) as live, httpx.Client(
            base_url=live.url, timeout=HTTP_TIMEOUT_S) as http:
        with pytest.raises(Interrupted):
            http.post("/api/cnc/sendFileStream", content=body(),
                      params={"machineID": "sim", "fileName": "HALF"},
                      headers={"X-Api-Key": API_KEY})
        live.wait_idle()

    assert list(storage(settings, "sim").iterdir()) == []
    # The client's doing, not the server's: no error and no traceback in the log.
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


def test_send_file_stream_failing_on_the_machine_mid_write_leaves_no_file(
        settings, assert_nothing_written, monkeypatch):
    def disk_fails(*args: object, **kwargs: object) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "link", disk_fails)  # the mock's last step: the name appears
    with TestClient(create_app(settings), headers={"X-Api-Key": API_KEY},
                    raise_server_exceptions=False) as client:
        response = client.post("/api/cnc/sendFileStream", content=b"x" * 300_000,
                               params={"machineID": "sim", "fileName": "HALF"})

    assert response.json()["errorCode"] == 20017
    assert_nothing_written()


def test_mock_write_whose_source_fails_midway_leaves_no_file(tmp_path):
    mock = MockTransport(MockOptions(), folder=tmp_path)

    def chunks() -> Iterator[bytes]:
        yield b"x" * 1000
        raise Dropped("link lost")

    with pytest.raises(Dropped):
        mock.write("HALF", chunks())

    assert list((tmp_path / "files").iterdir()) == []


def test_delete_of_the_running_program_is_refused_with_20008(client, settings, fleet):
    send(client, "sendFile", {"machineID": "run", "fileName": "P1"})

    body = client.get("/api/cnc/deleteFile", params={"machineID": "run", "fileName": "P1"}).json()

    assert body["errorCode"] == 20008
    assert (storage(settings, "run") / "P1").exists()


def test_delete_of_the_running_program_named_with_its_folder_is_refused(client, settings, fleet):
    send(client, "sendFile", {"machineID": "run", "fileName": "P1"})
    params = {"machineID": "run", "fileName": "P1", "dirAtCNC": "/"}

    body = client.get("/api/cnc/deleteFile", params=params).json()

    assert body["errorCode"] == 20008
    assert (storage(settings, "run") / "P1").exists()


def test_delete_of_the_running_program_with_force_deletes_it(client, settings, fleet):
    send(client, "sendFile", {"machineID": "run", "fileName": "P1"})
    params = {"machineID": "run", "fileName": "P1", "force": "true"}

    body = client.get("/api/cnc/deleteFile", params=params).json()

    assert body["errorCode"] == 0
    assert not (storage(settings, "run") / "P1").exists()


def test_a_link_to_the_api_key_in_a_mocks_storage_reaches_neither_a_read_nor_a_backup(
        queue_settings: Settings, celery_worker: Any) -> None:
    s = queue_settings.model_copy(update={"api_key": None})  # the key kept in the data folder
    key = s.effective_api_key(create=True)
    assert key is not None
    storage = s.data_dir / "mock" / "sim" / "files"
    storage.mkdir(parents=True)
    (storage / "key.nc").symlink_to(s.data_dir / "api-key")
    (storage / "data").symlink_to(s.data_dir)
    with db.session_scope(s.resolved_database_url) as session:
        registry.upsert(session=session, data_dir=s.data_dir, machine_in=registry.MachineIn(
            id="sim", name="Sim", model="Mock"))
    with TestClient(create_app(s), headers={"X-Api-Key": key}) as client:
        read = client.get("/api/cnc/receiveFile", params={"machineID": "sim",
                                                          "fileName": "key.nc"})
        listed = client.get("/api/cnc/readAllPrograms", params={"machineID": "sim"})
        backup = client.post("/api/cnc/backupFiles", json=[{"machineID": "sim"}])

    assert read.json()["errorCode"] == 20010 and key not in read.text
    assert listed.json()["programs"] == []
    assert key.encode() not in backup.content
