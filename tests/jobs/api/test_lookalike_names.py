"""Names and folders written with Unicode look-alikes of path syntax are refused like the real ones.

`．．／` (fullwidth), `‥` (two dot leader), `∕` (division slash) and `＼` (fullwidth reverse
solidus) read as `../`, `..`, `/` and `\\`: NFKC folds most of them, and tools on the way
(Windows' best-fit code pages) fold them too. The contract answers these with HTTP 200 and
its error body, as it answers the plain `..` and `/`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from jobs.settings import Settings

BAD_PARAMETER = 20001
PATH_OUTSIDE_ROOT = 20002
NAMES = ["\uff0e\uff0e\uff0fescaped.nc", "..\u2215escaped.nc", "..\uff3cescaped.nc", "\u2025",
         "a\uff0fb.nc", "a\u2044b.nc", "C\uff1aescaped.nc"]
DOT_DOT_FOLDERS = ["\uff0e\uff0e", "\u2025", "\uff0e\uff0e\uff0fescaped", "..\u2215escaped",
                   "..\uff3cescaped", "sub/\uff0e\uff0e/\uff0e\uff0e"]


@pytest.fixture
def sim(add_machines: Callable[..., Any], client: TestClient, settings: Settings) -> Path:
    """A mock machine `sim` holding P; returns the folder its storage lives in."""
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    client.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": "P"},
                json={"content": "G0\n"})
    return settings.data_dir / "mock"


def _files(storage: Path) -> list[str]:
    return sorted(p.relative_to(storage).as_posix() for p in storage.rglob("*")
                  if not p.name.startswith("state."))


def _error(response: Any) -> int:
    assert response.status_code == 200, response.text
    return int(response.json()["errorCode"])


@pytest.mark.parametrize("name", NAMES)
def test_send_with_a_look_alike_file_name_is_refused_and_writes_nothing(client, sim, name):
    before = _files(sim)

    sent = client.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": name},
                       json={"content": "G0\n"})

    assert _error(sent) == BAD_PARAMETER
    assert "reads as" in sent.json()["statusMsg"]
    assert _files(sim) == before


@pytest.mark.parametrize("name", [
    "\u202egpj.nc",  # a right-to-left override: shown as "cn.jpg"
    "P\u200b.nc", "\ufeffP.nc", "P\u2060.nc",  # zero-width space, byte order mark, joiner
    "\x85P.nc", "P\u2028.nc",  # a C1 control (NEL), a line separator
])
def test_a_name_with_an_invisible_or_control_character_is_refused_and_writes_nothing(
        client, sim, name):
    before = _files(sim)

    sent = client.post("/api/cnc/sendFile", params={"machineID": "sim", "fileName": name},
                       json={"content": "G0\n"})
    folder = client.get("/api/cnc/createDir", params={"machineID": "sim", "dirName": name})

    assert _error(sent) == _error(folder) == BAD_PARAMETER
    assert "control or invisible character" in sent.json()["statusMsg"]
    assert _files(sim) == before


@pytest.mark.parametrize("endpoint", ["receiveFile", "deleteFile", "selectProgram",
                                      "searchFile"])
@pytest.mark.parametrize("name", NAMES)
def test_look_alike_file_name_is_a_bad_parameter_in_every_endpoint(client, sim, endpoint, name):
    response = client.get(f"/api/cnc/{endpoint}", params={"machineID": "sim", "fileName": name})

    assert _error(response) == BAD_PARAMETER


@pytest.mark.parametrize("param", ["dirAtCNC", "subDir"])
@pytest.mark.parametrize("folder", DOT_DOT_FOLDERS)
def test_folder_that_reads_as_dot_dot_is_outside_the_root(client, sim, param, folder):
    response = client.get("/api/cnc/readProgramList", params={"machineID": "sim", param: folder})

    assert _error(response) == PATH_OUTSIDE_ROOT


@pytest.mark.parametrize("dir_name", ["\uff0e\uff0e", "a\u2215b", "a\uff3cb", "C\uff1a"])
def test_create_dir_with_a_look_alike_dir_name_is_refused_and_makes_nothing(client, sim,
                                                                            dir_name):
    before = _files(sim)

    response = client.get("/api/cnc/createDir", params={"machineID": "sim", "dirName": dir_name})

    assert _error(response) == BAD_PARAMETER
    assert _files(sim) == before


@pytest.mark.parametrize(("target", "code"), [
    ({"fileName": "\uff0e\uff0e\uff0fx.nc"}, BAD_PARAMETER),
    ({"fileName": "P", "DirAtCNC": "\uff0e\uff0e"}, PATH_OUTSIDE_ROOT),
    ({"fileName": "P", "SubDir": "..\u2215x"}, PATH_OUTSIDE_ROOT),
])
def test_job_target_with_a_look_alike_fails_at_its_position(client, sim, target, code):
    planned = client.post("/api/jobs", json={
        "kind": "send", "content": "G0\n", "dry_run": True,
        "targets": [{"machineID": "sim", "fileName": "OK.nc"}, {"machineID": "sim", **target}]})

    assert planned.status_code == 202, planned.text
    first, second = planned.json()["targets"]
    assert first["errorCode"] == 0
    assert (second["action"], second["errorCode"]) == ("fail", code)


def test_backup_of_a_folder_that_reads_as_dot_dot_is_refused(client, sim):
    response = client.post("/api/cnc/backupFiles",
                           json=[{"machineID": "sim", "dirAtCNC": "\uff0e\uff0e\uff0f"}])

    assert _error(response) == PATH_OUTSIDE_ROOT


@pytest.mark.parametrize("folder", ["\uff0e\uff0e", "\u2025/x", "a\uff0f\uff0e\uff0e"])
def test_schedule_with_a_folder_that_reads_as_dot_dot_answers_400(client, folder):
    response = client.post("/api/schedules", json={"name": "nightly", "cron": "0 2 * * *",
                                                   "dirAtCNC": folder})

    assert response.status_code == 400, response.text
    assert response.json()["errorCode"] == BAD_PARAMETER
    assert client.get("/api/schedules").json() == []
