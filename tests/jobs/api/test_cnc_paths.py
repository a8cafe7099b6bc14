"""Path rules of the file API (contract.md "Paths"), through HTTP against mock machines."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

FANUC_0010 = "%\nO0010\nG0 X0\nM30\n%\n"
GCODE = "G0 X0\nM30\n"

PATH_NOT_FOUND = 158
BAD_PARAMETER = 20001
PATH_OUTSIDE_ROOT = 20002
UNSUPPORTED = 20003


@pytest.fixture
def machine(add_machines) -> Callable[..., str]:
    """Factory: a mock machine of `model` (plus fleet-file fields); returns its id."""
    ids = itertools.count(1)

    def make(model: str, **fields: Any) -> str:
        machine_id = f"m{next(ids)}"
        add_machines({"id": machine_id, "name": f"test-{machine_id}", "model": model,
                      "transport": "mock", **fields})
        return machine_id

    return make


def call(client, endpoint: str, machine_id: str, **params: Any) -> dict[str, Any]:
    """GET /api/cnc/<endpoint>; the contract answers its own errors with HTTP 200."""
    response = client.get(f"/api/cnc/{endpoint}", params={"machineID": machine_id, **params})
    assert response.status_code == 200, response.text
    return response.json()


def send(client, machine_id: str, content: str, **params: Any) -> dict[str, Any]:
    response = client.post("/api/cnc/sendFile", params={"machineID": machine_id, **params},
                           json={"content": content})
    assert response.status_code == 200, response.text
    return response.json()


def ok(body: dict[str, Any]) -> None:
    assert body == {"errorCode": 0, "errorMsg": "Success"}


def listing(client, machine_id: str, **params: Any) -> dict[str, Any]:
    return call(client, "readProgramList", machine_id, **params)


# -- neither, only subDir, both ------------------------------------------------


@pytest.mark.parametrize(("model", "root"), [
    ("Fanuc 0i-F", "//CNC_MEM/"), ("Fanuc 18i", "//CNC_MEM/"), ("Siemens 840D", "mpf.dir"),
    ("Heidenhain TNC640", "TNC:\\nc_prog"), ("Mitsubishi M800", "PRG\\USER\\"),
    ("Mitsubishi", "PRG\\USER\\"), ("Brother S", "/"), ("Brother TC", "/"), ("Mock", "/"),
    ("Other", ""),
])
def test_no_folder_lists_the_default_root_and_returns_it(client, machine, model, root):
    body = listing(client, machine(model))
    assert body == {"dirAtCNC": root, "programs": [], "subDirs": []}


def test_no_folder_lists_the_files_of_the_default_root(client, machine):
    m = machine("Siemens 840D")
    ok(send(client, m, GCODE, fileName="PART1.MPF"))
    assert listing(client, m)["programs"] == ["PART1.MPF"]


def test_empty_dir_at_cnc_is_the_default_root(client, machine):
    m = machine("Siemens 840D")
    ok(send(client, m, GCODE, fileName="PART1.MPF"))
    assert listing(client, m, dirAtCNC="") == listing(client, m)


def test_sub_dir_alone_is_joined_to_the_root(client, machine):
    m = machine("Siemens 840D")
    ok(call(client, "createDir", m, dirName="dir1"))
    ok(send(client, m, GCODE, fileName="IN_DIR1.MPF", subDir="dir1"))
    assert listing(client, m, subDir="dir1") == {
        "dirAtCNC": "mpf.dir/dir1", "programs": ["IN_DIR1.MPF"], "subDirs": []}


def test_sub_dir_is_ignored_when_dir_at_cnc_is_given(client, machine):
    m = machine("Fanuc 0i-F")
    ok(call(client, "createDir", m, dirName="USER"))
    ok(send(client, m, FANUC_0010, dirAtCNC="//CNC_MEM/USER", subDir="NOT_THERE"))
    body = listing(client, m, dirAtCNC="//CNC_MEM/USER", subDir="NOT_THERE")
    assert body == {"dirAtCNC": "//CNC_MEM/USER", "programs": ["10"], "subDirs": []}


def test_relative_dir_at_cnc_is_below_the_default_root(client, machine):
    m = machine("Siemens 840D")
    ok(call(client, "createDir", m, dirName="dir1"))
    ok(send(client, m, GCODE, fileName="sample.NC", dirAtCNC="dir1"))
    body = listing(client, m, dirAtCNC="dir1")
    assert body == {"dirAtCNC": "mpf.dir/dir1", "programs": ["sample.NC"], "subDirs": []}


def test_relative_and_rooted_dir_at_cnc_reach_the_same_folder(client, machine):
    m = machine("Siemens 840D")
    ok(call(client, "createDir", m, dirName="dir1"))
    ok(send(client, m, GCODE, fileName="sample.NC", dirAtCNC="dir1"))
    assert call(client, "receiveFile", m, fileName="sample.NC", dirAtCNC="mpf.dir/dir1") \
        == {"content": GCODE, "encoding": "us-ascii"}


# -- rooted, corrected, alternative roots --------------------------------------


@pytest.mark.parametrize(("model", "parent", "folder", "as_written"), [
    ("Fanuc 0i-F", None, "USER", "//CNC_MEM/USER"),
    ("Heidenhain TNC640", None, "demo", "TNC:\\nc_prog\\demo"),
    ("Mock", "/", "1", "/1"),
])
def test_rooted_dir_at_cnc_is_taken_as_written(client, machine, model, parent, folder,
                                               as_written):
    m = machine(model)
    ok(call(client, "createDir", m, dirName=folder, **({"dirAtCNC": parent} if parent else {})))
    assert listing(client, m, dirAtCNC=as_written)["dirAtCNC"] == as_written


def test_mitsubishi_card_ic1_is_taken_as_written(client, machine):
    m = machine("Mitsubishi M800")
    ok(send(client, m, GCODE, fileName="200", dirAtCNC="IC1"))
    assert listing(client, m, dirAtCNC="IC1") == {
        "dirAtCNC": "IC1", "programs": ["200"], "subDirs": []}
    assert listing(client, m)["programs"] == []


@pytest.mark.parametrize(("model", "folder", "written", "corrected"), [
    ("Heidenhain TNC640", "demo", "TNC:/nc_prog/demo", "TNC:\\nc_prog\\demo"),
    ("Fanuc 0i-F", "USER", "//cnc_mem/USER", "//CNC_MEM/USER"),
    ("Fanuc 0i-F", "USER", "//CNC_MEM/USER/", "//CNC_MEM/USER"),
    ("Siemens 840D", "dir1", "MPF.DIR/dir1", "mpf.dir/dir1"),
])
def test_existing_path_in_the_wrong_notation_is_returned_corrected(client, machine, model,
                                                                   folder, written, corrected):
    m = machine(model)
    ok(call(client, "createDir", m, dirName=folder))
    assert listing(client, m, dirAtCNC=written)["dirAtCNC"] == corrected


def test_mitsubishi_card_written_in_lower_case_is_returned_as_ic1(client, machine):
    m = machine("Mitsubishi M800")
    assert listing(client, m, dirAtCNC="ic1")["dirAtCNC"] == "IC1"


def test_missing_folder_is_path_not_found(client, machine):
    m = machine("Fanuc 0i-F")
    body = listing(client, m, dirAtCNC="//CNC_MEM/NOPE")
    assert (body["errorCode"], body["errorMsg"]) == (PATH_NOT_FOUND, "Path is not found.")


def test_heidenhain_drive_root_lists_nc_prog_as_a_subfolder(client, machine):
    m = machine("Heidenhain TNC640")
    assert listing(client, m, dirAtCNC="TNC:\\") == {
        "dirAtCNC": "TNC:\\", "programs": [], "subDirs": ["nc_prog"]}


def test_fanuc_0i_f_reaches_the_memory_card(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, FANUC_0010, dirAtCNC="//MEMCARD/"))
    assert listing(client, m, dirAtCNC="//MEMCARD/") == {
        "dirAtCNC": "//MEMCARD/", "programs": ["10"], "subDirs": []}
    assert listing(client, m)["programs"] == []


def test_fanuc_0i_d_refuses_the_memory_card(client, machine):
    m = machine("Fanuc 0i-D")
    assert listing(client, m, dirAtCNC="//MEMCARD/")["errorCode"] == PATH_OUTSIDE_ROOT


def test_configured_root_is_the_default_root(client, machine):
    m = machine("Fanuc 0i-F", root="//MEMCARD/")
    ok(send(client, m, FANUC_0010))
    assert listing(client, m) == {"dirAtCNC": "//MEMCARD/", "programs": ["10"], "subDirs": []}
    assert listing(client, m, dirAtCNC="//CNC_MEM/")["programs"] == []


def test_configured_root_spelt_in_lower_case_reaches_the_models_folder(client, machine):
    m = machine("Fanuc 0i-F", root="//memcard/")
    ok(send(client, m, FANUC_0010))
    assert listing(client, m, dirAtCNC="//MEMCARD/") == {
        "dirAtCNC": "//MEMCARD/", "programs": ["10"], "subDirs": []}


def test_mitsubishi_with_card_as_root_creates_folders_without_dir_at_cnc(client, machine):
    m = machine("Mitsubishi M800", root="IC1")
    ok(call(client, "createDir", m, dirName="NEW"))
    assert listing(client, m, dirAtCNC="IC1\\NEW")["dirAtCNC"] == "IC1\\NEW"


def test_mitsubishi_with_a_folder_on_the_card_as_root_creates_folders_there(client, machine,
                                                                              settings):
    (settings.data_dir / "mock" / "m1" / "files" / "IC1" / "PROG").mkdir(parents=True)
    m = machine("Mitsubishi M800", root="IC1\\PROG")
    ok(call(client, "createDir", m, dirName="NEW"))
    assert listing(client, m, dirAtCNC="IC1\\PROG\\NEW")["dirAtCNC"] == "IC1\\PROG\\NEW"


def test_mock_with_a_configured_root_folder_lists_it(client, machine):
    m = machine("Mock", root="/programs")
    ok(send(client, m, GCODE, fileName="A.nc"))
    assert listing(client, m) == {"dirAtCNC": "/programs", "programs": ["A.nc"], "subDirs": []}
    assert listing(client, m, dirAtCNC="/")["subDirs"] == ["programs"]


def test_query_parameters_written_in_another_case_name_the_same_file(client, machine):
    m = machine("Mock")
    ok(call(client, "createDir", m, dirName="1"))
    ok(send(client, m, GCODE, fileName="A.nc"))
    ok(send(client, m, GCODE, fileName="A.nc", dirAtCNC="1"))

    # the spelling of the seed's batch targets (DirAtCNC, SubDir), on a single file's request
    deleted = client.get("/api/cnc/deleteFile",
                         params={"machineID": m, "fileName": "A.nc", "DirAtCNC": "1"})

    ok(deleted.json())
    assert listing(client, m, dirAtCNC="1")["programs"] == []
    assert listing(client, m)["programs"] == ["A.nc"]  # the root's file is still there


# -- models with no target folder ------------------------------------------------


@pytest.mark.parametrize("model", ["Fanuc 18i", "Brother TC", "Other"])
@pytest.mark.parametrize("param", ["dirAtCNC", "subDir"])
def test_model_without_target_folder_refuses_a_folder_as_unsupported(client, machine, model,
                                                                     param):
    body = listing(client, machine(model), **{param: "dir1"})
    assert body["errorCode"] == UNSUPPORTED


@pytest.mark.parametrize("model", ["Fanuc 18i", "Brother TC", "Other"])
def test_model_without_target_folder_refuses_a_send_into_a_folder(client, machine, model):
    content = FANUC_0010 if model.startswith("Fanuc") else GCODE
    body = send(client, machine(model), content, fileName="A.nc", dirAtCNC="dir1")
    assert body["errorCode"] == UNSUPPORTED


# -- unsafe paths and names ----------------------------------------------------------


@pytest.mark.parametrize(("param", "value"), [("dirAtCNC", "../x"), ("subDir", "a/../../x"),
                                              ("dirAtCNC", "/1/../..")])
def test_dot_dot_in_a_folder_is_refused(client, machine, param, value):
    assert listing(client, machine("Mock"), **{param: value})["errorCode"] == PATH_OUTSIDE_ROOT


@pytest.mark.parametrize(("model", "foreign"), [("Fanuc 0i-F", "/etc"),
                                                ("Siemens 840D", "/nckfs"),
                                                ("Heidenhain TNC640", "C:\\Windows")])
def test_rooted_folder_outside_the_models_roots_is_refused(client, machine, model, foreign):
    assert listing(client, machine(model), dirAtCNC=foreign)["errorCode"] == PATH_OUTSIDE_ROOT


@pytest.mark.parametrize("name", ["a/b.nc", "a\\b.nc", "..", "C:b.nc"])
def test_file_name_that_is_a_path_is_a_bad_parameter(client, machine, name):
    m = machine("Mock")
    assert send(client, m, GCODE, fileName=name)["errorCode"] == BAD_PARAMETER
    assert call(client, "receiveFile", m, fileName=name)["errorCode"] == BAD_PARAMETER


def test_file_name_that_is_a_path_does_not_write_anything(client, machine, settings):
    m = machine("Mock")
    send(client, m, GCODE, fileName="../escaped.nc")
    files: Path = settings.data_dir / "mock" / m
    assert not list(files.rglob("escaped.nc"))


def test_the_contracts_paths_are_taken_in_any_case_and_audited_as_written(client, machine):
    # The gateway's routing takes any case: /api/cnc/ReadProgramList was 404 with 158,
    # "Path is not found.", which a client reads as a missing file.
    m = machine("Mock")
    client.post("/api/cnc/sendFile", params={"machineID": m, "fileName": "A.nc"},
                json={"content": "G0 X0\n"})

    listed = client.get("/api/cnc/ReadProgramList", params={"machineID": m})
    deleted = client.get("/API/CNC/DELETEFILE", params={"machineID": m, "fileName": "A.nc"})

    assert "A.nc" in listed.json()["programs"], listed.text
    assert deleted.json()["errorCode"] == 0, deleted.text
    audited = [e["action"] for e in client.get("/api/audit").json()]
    assert "cnc.deleteFile" in audited, audited
