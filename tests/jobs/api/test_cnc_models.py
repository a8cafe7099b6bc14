"""Model-specific behaviour of the file API (tables 55-57, Fanuc naming, 2.6.10/2.6.14),
through HTTP against mock machines."""

from __future__ import annotations

import base64
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.jobs.helpers import mock_of

PATH_EXISTS = 142
PATH_NOT_FOUND = 158
BAD_PARAMETER = 20001
UNSUPPORTED = 20003
DIR_NOT_EMPTY = 20009

GCODE = "G0 X0\nM30\n"


def fanuc(number: str, body: str = "G0 X0\nM30\n") -> str:
    """Fanuc program text whose name (between first and second newline) is `O<number>`."""
    return f"%\nO{number}\n{body}%\n"


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


@pytest.fixture
def storage(settings) -> Callable[[str], Path]:
    """The folder holding a mock machine's storage, for what the API cannot set up."""
    return lambda machine_id: settings.data_dir / "mock" / machine_id / "files"


def call(client, endpoint: str, machine_id: str, **params: Any) -> dict[str, Any]:
    """GET /api/cnc/<endpoint>; the contract answers its own errors with HTTP 200."""
    response = client.get(f"/api/cnc/{endpoint}", params={"machineID": machine_id, **params})
    assert response.status_code == 200, response.text
    return response.json()


def send(client, machine_id: str, content: str | None = None, *, b64: str | None = None,
         **params: Any) -> dict[str, Any]:
    body = {k: v for k, v in (("content", content), ("base64", b64)) if v is not None}
    response = client.post("/api/cnc/sendFile", params={"machineID": machine_id, **params},
                           json=body)
    assert response.status_code == 200, response.text
    return response.json()


def send_stream(client, machine_id: str, data: bytes, **params: Any) -> dict[str, Any]:
    response = client.post("/api/cnc/sendFileStream", content=data,
                           params={"machineID": machine_id, **params},
                           headers={"Content-Type": "application/octet-stream"})
    assert response.status_code == 200, response.text
    return response.json()


def receive_stream(client, machine_id: str, **params: Any) -> bytes:
    response = client.get("/api/cnc/receiveFileStream", params={"machineID": machine_id, **params})
    assert response.status_code == 200, response.text
    return response.content


def ok(body: dict[str, Any]) -> None:
    assert body == {"errorCode": 0, "errorMsg": "Success"}


def code(body: dict[str, Any]) -> int:
    return body["errorCode"]


def programs(client, machine_id: str, **params: Any) -> list[str]:
    return call(client, "readProgramList", machine_id, **params)["programs"]


# -- Fanuc naming ------------------------------------------------------------------


def test_fanuc_send_file_ignores_file_name_and_takes_the_name_from_the_content(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0020"), fileName="IGNORED"))
    assert programs(client, m) == ["20"]


def test_fanuc_program_o0000_is_refused_as_a_control_refuses_it(client, machine):
    m = machine("Fanuc 0i-F")
    assert code(send(client, m, fanuc("0000"), fileName="IGNORED")) == BAD_PARAMETER
    assert code(call(client, "receiveFile", m, fileName="0")) == BAD_PARAMETER
    assert programs(client, m) == []


def test_fanuc_send_file_stream_ignores_file_name_and_takes_the_name_from_the_content(
    client, machine
):
    m = machine("Fanuc 0i-F")
    ok(send_stream(client, m, fanuc("0020").encode(), fileName="O9999"))
    assert programs(client, m) == ["20"]


@pytest.mark.parametrize("file_name", ["../../O0020", "a/b", "a\\b", "x\x00"])
def test_a_fanuc_send_whose_file_name_is_a_path_is_refused_though_the_name_is_ignored(
        client, machine, file_name: str):
    # The content names the program, but a fileName that is no name is refused on every
    # model alike: a client finds its mistake here, not on the next machine.
    m = machine("Fanuc 0i-F")
    assert code(send(client, m, fanuc("0020"), fileName=file_name)) == BAD_PARAMETER
    assert programs(client, m) == []


def test_fanuc_send_needs_no_file_name(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0020")))
    assert programs(client, m) == ["20"]


def test_fanuc_send_without_a_program_name_in_the_content_is_a_bad_parameter(client, machine):
    m = machine("Fanuc 0i-F")
    assert code(send(client, m, "%\nG0 X0\nM30\n%\n", fileName="O0020")) == BAD_PARAMETER
    assert programs(client, m) == []


def test_fanuc_listing_drops_o_and_leading_zeros(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010")))
    assert programs(client, m) == ["10"]


def test_fanuc_listing_keeps_a_non_standard_name(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, "%\n<SAMPLE>\nG0 X0\nM30\n%\n"))
    assert programs(client, m) == ["SAMPLE"]


def test_fanuc_non_standard_name_is_received_as_listed(client, machine):
    m = machine("Fanuc 0i-F")
    content = "%\n<SAMPLE>\nG0 X0\nM30\n%\n"
    ok(send(client, m, content))
    assert call(client, "receiveFile", m, fileName="SAMPLE")["content"] == content


def test_fanuc_18i_lists_the_o_number_unchanged(client, machine):
    m = machine("Fanuc 18i")
    ok(send(client, m, fanuc("0010")))
    assert programs(client, m) == ["O0010"]


def test_fanuc_18i_takes_the_name_from_the_content_too(client, machine):
    m = machine("Fanuc 18i")
    ok(send(client, m, fanuc("0010"), fileName="IGNORED"))
    assert call(client, "receiveFile", m, fileName="O0010")["content"] == fanuc("0010")


SPELLINGS = ["10", "010", "0010", "O0010"]


@pytest.mark.parametrize("spelling", SPELLINGS)
def test_fanuc_receive_file_accepts_every_spelling(client, machine, spelling):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010")))
    assert call(client, "receiveFile", m, fileName=spelling) == {
        "content": fanuc("0010"), "encoding": "us-ascii"}


def test_fanuc_program_numbers_are_ascii_digits_only(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010")))
    assert call(client, "receiveFile", m, fileName="\u0661\u0660")["errorCode"] == 158  # ١٠


@pytest.mark.parametrize("spelling", SPELLINGS)
def test_fanuc_receive_file_stream_accepts_every_spelling(client, machine, spelling):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010")))
    assert receive_stream(client, m, fileName=spelling) == fanuc("0010").encode()


@pytest.mark.parametrize("spelling", SPELLINGS)
def test_fanuc_delete_file_accepts_every_spelling(client, machine, spelling):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010")))
    ok(call(client, "deleteFile", m, fileName=spelling))
    assert programs(client, m) == []


@pytest.mark.parametrize("spelling", SPELLINGS)
def test_fanuc_select_program_accepts_every_spelling(client, machine, spelling):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010")))
    ok(call(client, "selectProgram", m, fileName=spelling))
    assert call(client, "readCurrentProgram", m)["fileName"] == "10"


@pytest.mark.parametrize("spelling", SPELLINGS)
def test_fanuc_search_file_accepts_every_spelling(client, machine, spelling):
    m = machine("Fanuc 0i-F")
    ok(call(client, "createDir", m, dirName="USER"))
    ok(send(client, m, fanuc("0010"), dirAtCNC="//CNC_MEM/USER"))
    assert call(client, "searchFile", m, fileName=spelling) == {
        "dirAtCNC": "//CNC_MEM/USER", "programs": ["10"], "subDirs": []}


# -- no overwrite --------------------------------------------------------------------


def test_second_send_of_the_same_name_is_path_exists_and_keeps_the_original(client, machine):
    m = machine("Mock")
    ok(send(client, m, "first\n", fileName="A.nc"))
    body = send(client, m, "second\n", fileName="A.nc")
    assert (body["errorCode"], body["errorMsg"]) == (PATH_EXISTS, "Path exists.")
    assert call(client, "receiveFile", m, fileName="A.nc")["content"] == "first\n"


def test_second_send_file_stream_of_the_same_name_is_path_exists_and_keeps_the_original(
    client, machine
):
    m = machine("Siemens 840D")
    ok(send_stream(client, m, b"first\n", fileName="A.MPF"))
    assert code(send_stream(client, m, b"second\n", fileName="A.MPF")) == PATH_EXISTS
    assert receive_stream(client, m, fileName="A.MPF") == b"first\n"


def test_fanuc_second_send_of_the_same_program_number_is_path_exists(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010", "G0 X1\n"), fileName="A"))
    assert code(send(client, m, fanuc("10", "G0 X2\n"), fileName="B")) == PATH_EXISTS
    assert call(client, "receiveFile", m, fileName="10")["content"] == fanuc("0010", "G0 X1\n")


# -- subfolder listing (table 56) ------------------------------------------------------


@pytest.mark.parametrize(("model", "folder"), [
    ("Siemens 840D", "dir1"), ("Heidenhain TNC640", "demo"), ("Mock", "1"),
    ("Fanuc 0i-F", "USER"), ("Brother S", "sub"),
])
def test_listing_returns_subfolders_where_table_56_says_so(client, machine, model, folder):
    m = machine(model)
    ok(call(client, "createDir", m, dirName=folder))
    assert call(client, "readProgramList", m)["subDirs"] == [folder]


@pytest.mark.parametrize(("model", "folder"), [
    ("Mitsubishi M800", "PRG/USER/sub"), ("Mitsubishi", "PRG/USER/sub"),
    ("Fanuc 18i", "CNC_MEM/sub"),
])
def test_listing_returns_no_subfolders_where_table_56_says_so(client, machine, storage, model,
                                                              folder):
    m = machine(model)
    (storage(m) / folder).mkdir(parents=True)
    assert call(client, "readProgramList", m)["subDirs"] == []


def test_mitsubishi_lists_no_subfolders_on_the_card_either(client, machine):
    m = machine("Mitsubishi M800")
    ok(call(client, "createDir", m, dirName="NEW", dirAtCNC="IC1"))
    assert call(client, "readProgramList", m, dirAtCNC="IC1")["subDirs"] == []


def test_mitsubishi_read_all_programs_does_not_walk_into_subfolders(client, machine, storage):
    m = machine("Mitsubishi M800")
    ok(send(client, m, GCODE, fileName="100"))
    (storage(m) / "PRG/USER/sub").mkdir()
    (storage(m) / "PRG/USER/sub/200").write_text(GCODE)
    assert call(client, "readAllPrograms", m) == {
        "programs": [{"dirAtCNC": "/", "fileName": "100"}]}


# -- createDir / deleteDir (table 57) ----------------------------------------------------


@pytest.mark.parametrize("model", ["Fanuc 0i-F", "Siemens 840D", "Heidenhain TNC640", "Mock",
                                   "Brother S"])
def test_create_dir_makes_a_folder_where_table_57_says_so(client, machine, model):
    m = machine(model)
    ok(call(client, "createDir", m, dirName="NEW"))
    assert call(client, "readProgramList", m)["subDirs"] == ["NEW"]


@pytest.mark.parametrize("model", ["Fanuc 18i", "Brother TC", "Mitsubishi", "Other"])
def test_create_dir_is_unsupported_where_table_57_says_so(client, machine, storage, model):
    m = machine(model)
    assert code(call(client, "createDir", m, dirName="NEW")) == UNSUPPORTED
    assert not list(storage(m).rglob("NEW"))


@pytest.mark.parametrize("model", ["Fanuc 18i", "Brother TC"])
def test_delete_dir_is_unsupported_where_table_57_says_so(client, machine, storage, model):
    m = machine(model)
    root = "CNC_MEM" if model.startswith("Fanuc") else ""
    (storage(m) / root / "OLD").mkdir(parents=True)
    assert code(call(client, "deleteDir", m, dirName="OLD")) == UNSUPPORTED
    assert (storage(m) / root / "OLD").is_dir()


def test_mitsubishi_creates_a_folder_on_the_card(client, machine):
    m = machine("Mitsubishi M800")
    ok(call(client, "createDir", m, dirName="NEW", dirAtCNC="IC1"))
    assert call(client, "readProgramList", m, dirAtCNC="IC1\\NEW")["dirAtCNC"] == "IC1\\NEW"


def test_mitsubishi_refuses_a_folder_outside_the_card(client, machine, storage):
    m = machine("Mitsubishi M800")
    assert code(call(client, "createDir", m, dirName="NEW")) == UNSUPPORTED
    assert not (storage(m) / "PRG/USER/NEW").exists()


def test_mitsubishi_deletes_an_empty_folder_on_the_card(client, machine):
    m = machine("Mitsubishi M800")
    ok(call(client, "createDir", m, dirName="OLD", dirAtCNC="IC1"))
    ok(call(client, "deleteDir", m, dirName="OLD", dirAtCNC="IC1"))
    assert code(call(client, "readProgramList", m, dirAtCNC="IC1\\OLD")) == PATH_NOT_FOUND


def test_mitsubishi_refuses_to_delete_a_folder_outside_the_card(client, machine, storage):
    m = machine("Mitsubishi M800")
    (storage(m) / "PRG/USER/OLD").mkdir(parents=True)
    assert code(call(client, "deleteDir", m, dirName="OLD")) == UNSUPPORTED
    assert (storage(m) / "PRG/USER/OLD").is_dir()


def test_delete_dir_removes_an_empty_folder(client, machine):
    m = machine("Mock")
    ok(call(client, "createDir", m, dirName="OLD"))
    ok(call(client, "deleteDir", m, dirName="OLD"))
    assert call(client, "readProgramList", m)["subDirs"] == []


def test_delete_dir_of_a_non_empty_folder_is_refused_and_keeps_it(client, machine):
    m = machine("Mock")
    ok(call(client, "createDir", m, dirName="FULL"))
    ok(send(client, m, GCODE, fileName="A.nc", subDir="FULL"))
    assert code(call(client, "deleteDir", m, dirName="FULL")) == DIR_NOT_EMPTY
    assert call(client, "readProgramList", m, subDir="FULL")["programs"] == ["A.nc"]


def test_delete_dir_of_a_missing_folder_is_path_not_found(client, machine):
    m = machine("Mock")
    assert code(call(client, "deleteDir", m, dirName="NOPE")) == PATH_NOT_FOUND


def test_create_dir_of_an_existing_folder_is_path_exists(client, machine):
    m = machine("Mock")
    ok(call(client, "createDir", m, dirName="NEW"))
    assert code(call(client, "createDir", m, dirName="NEW")) == PATH_EXISTS


# -- lockFileByRange (2.6.10) ------------------------------------------------------------


def lock(client, machine_id: str, start: int, end: int, is_lock: bool = True) -> dict[str, Any]:
    return call(client, "lockFileByRange", machine_id, isLock=str(is_lock).lower(),
                lockStart=start, lockEnd=end)


LOCK_MODELS = ["Fanuc 0i-F", "Fanuc 18i", "Mitsubishi M800", "Mitsubishi"]


@pytest.mark.parametrize("model", LOCK_MODELS)
@pytest.mark.parametrize(("start", "end"), [(8000, 8999), (9000, 9999), (8000, 9999)])
@pytest.mark.parametrize("is_lock", [True, False])
def test_lock_file_by_range_locks_and_unlocks_the_three_ranges(client, settings, machine,
                                                               model, start, end, is_lock):
    machine_id = machine(model)
    if not is_lock:  # unlocking takes a range that was locked
        ok(lock(client, machine_id, start, end, True))
    ok(lock(client, machine_id, start, end, is_lock))
    locked = mock_of(settings, machine_id).locked_ranges()
    assert ((start, end) in locked) is is_lock


@pytest.mark.parametrize("model", LOCK_MODELS)
@pytest.mark.parametrize(("start", "end"), [(8000, 8998), (7000, 7999), (9999, 9000),
                                            (0, 9999), (8000, 10000), (8500, 8999)])
def test_lock_file_by_range_refuses_any_other_range_as_bad_parameter(client, machine, model,
                                                                     start, end):
    assert code(lock(client, machine(model), start, end)) == BAD_PARAMETER


@pytest.mark.parametrize("model", ["Siemens 840D", "Heidenhain TNC640", "Brother S", "Mock"])
def test_lock_file_by_range_is_unsupported_on_other_models(client, machine, model):
    assert code(lock(client, machine(model), 8000, 8999)) == UNSUPPORTED


PERMISSION_DENIED = 20010
# A program in 8000-8999 as each model names it in fileName and in its content.
LOCKED_PROGRAM = {"Fanuc 0i-F": ("8999", fanuc("8999")), "Mitsubishi M800": ("8999", GCODE)}


def locked_machine(client, machine, model: str) -> str:
    """A machine of `model` holding program 8999, with 8000-8999 locked."""
    m = machine(model)
    name, content = LOCKED_PROGRAM[model]
    ok(send(client, m, content, fileName=name))
    ok(lock(client, m, 8000, 8999))
    return m


@pytest.mark.parametrize("model", LOCKED_PROGRAM)
def test_a_program_in_a_locked_range_cannot_be_deleted(client, machine, model):
    m = locked_machine(client, machine, model)
    refused = call(client, "deleteFile", m, fileName="8999")
    assert code(refused) == PERMISSION_DENIED and "8000-8999" in refused["statusMsg"]
    assert "8999" in " ".join(programs(client, m))


@pytest.mark.parametrize("model", LOCKED_PROGRAM)
def test_a_program_in_a_locked_range_cannot_be_sent_new_or_replacing(client, machine, model):
    m = locked_machine(client, machine, model)
    ok(lock(client, m, 9000, 9999))
    new = send(client, m, fanuc("9001") if model.startswith("Fanuc") else GCODE,
               fileName="9001")
    name, _ = LOCKED_PROGRAM[model]
    replacing = send(client, m, LOCKED_PROGRAM[model][1].replace("M30", "M02"),
                     fileName=name, replace="true")
    assert code(new) == PERMISSION_DENIED and "9000-9999" in new["statusMsg"]
    assert code(replacing) == PERMISSION_DENIED and "8000-8999" in replacing["statusMsg"]
    assert call(client, "receiveFile", m, fileName=name)["content"] == LOCKED_PROGRAM[model][1]


@pytest.mark.parametrize("model", LOCKED_PROGRAM)
def test_a_program_in_a_locked_range_can_still_be_read(client, machine, model):
    m = locked_machine(client, machine, model)
    name, content = LOCKED_PROGRAM[model]
    assert call(client, "receiveFile", m, fileName=name)["content"] == content


@pytest.mark.parametrize("model", LOCKED_PROGRAM)
def test_unlocking_a_range_lets_its_programs_be_deleted_and_sent_again(client, machine, model):
    m = locked_machine(client, machine, model)
    name, content = LOCKED_PROGRAM[model]
    assert code(call(client, "deleteFile", m, fileName=name)) == PERMISSION_DENIED
    ok(lock(client, m, 8000, 8999, is_lock=False))
    ok(call(client, "deleteFile", m, fileName=name))
    ok(send(client, m, content, fileName=name))


def test_a_lock_leaves_programs_outside_its_range_free(client, machine):
    m = locked_machine(client, machine, "Fanuc 0i-F")
    ok(send(client, m, fanuc("9001")))
    ok(call(client, "deleteFile", m, fileName="9001"))


# -- selectProgram (2.6.14) and readCurrentProgram (2.6.4) --------------------------------


def test_mock_read_current_program_without_a_current_program_is_no_content(client, machine):
    assert call(client, "readCurrentProgram", machine("Mock")) == {
        "errorCode": PATH_NOT_FOUND, "errorMsg": "Path is not found.", "statusMsg": "No content."}


def test_mock_select_program_succeeds_for_a_file_that_does_not_exist(client, machine):
    ok(call(client, "selectProgram", machine("Mock"), fileName="NOPE.nc"))


def test_mock_select_program_changes_nothing(client, machine):
    m = machine("Mock")
    ok(send(client, m, GCODE, fileName="A.nc"))
    ok(call(client, "selectProgram", m, fileName="A.nc"))
    assert code(call(client, "readCurrentProgram", m)) == PATH_NOT_FOUND


def test_mock_with_a_current_program_option_reads_it(client, machine):
    m = machine("Mock", options={"current_program": "/A.nc"})
    ok(send(client, m, GCODE, fileName="A.nc"))
    assert call(client, "readCurrentProgram", m) == {
        "dirAtCNC": "/", "fileName": "A.nc", "content": GCODE, "encoding": "us-ascii"}


@pytest.mark.parametrize("where", [{"dirAtCNC": ".."}, {"subDir": "../x"},
                                   {"dirAtCNC": "/a/../.."}])
def test_read_current_program_checks_its_folder_parameters_as_every_endpoint(client, machine,
                                                                              where):
    m = machine("Mock", options={"current_program": "/A.nc"})
    ok(send(client, m, GCODE, fileName="A.nc"))

    refused = call(client, "readCurrentProgram", m, **where)

    assert code(refused) != 0 and code(refused) == code(call(client, "readProgramList", m, **where))
    assert call(client, "readCurrentProgram", m, dirAtCNC="/")["fileName"] == "A.nc"


def test_fanuc_select_program_makes_it_the_current_program(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010")))
    ok(call(client, "selectProgram", m, fileName="10"))
    assert call(client, "readCurrentProgram", m) == {
        "dirAtCNC": "//CNC_MEM/", "fileName": "10", "content": fanuc("0010"),
        "encoding": "us-ascii"}


def test_fanuc_select_program_in_a_subfolder_reads_back_that_folder(client, machine):
    m = machine("Fanuc 0i-F")
    ok(call(client, "createDir", m, dirName="USER"))
    ok(send(client, m, fanuc("0010"), dirAtCNC="//CNC_MEM/USER"))
    ok(call(client, "selectProgram", m, fileName="10", dirAtCNC="//CNC_MEM/USER"))
    assert call(client, "readCurrentProgram", m)["dirAtCNC"] == "//CNC_MEM/USER"


def test_fanuc_select_program_of_a_missing_file_is_path_not_found(client, machine):
    m = machine("Fanuc 0i-F")
    assert code(call(client, "selectProgram", m, fileName="10")) == PATH_NOT_FOUND
    assert code(call(client, "readCurrentProgram", m)) == PATH_NOT_FOUND


def test_brother_s_select_program_makes_it_the_current_program(client, machine):
    m = machine("Brother S")
    ok(send(client, m, GCODE, fileName="O1000.NC"))
    ok(call(client, "selectProgram", m, fileName="O1000.NC"))
    assert call(client, "readCurrentProgram", m)["fileName"] == "O1000.NC"


@pytest.mark.parametrize(("model", "file_name", "content"), [
    ("Siemens 840D", "PART1.MPF", GCODE),
    ("Heidenhain TNC640", "PLATE.h", GCODE),
    ("Fanuc 18i", "O0010", fanuc("0010")),
    ("Mitsubishi M800", "100", GCODE),
])
def test_select_program_is_unsupported_on_other_models(client, machine, model, file_name,
                                                       content):
    m = machine(model)
    ok(send(client, m, content, fileName=file_name))
    assert code(call(client, "selectProgram", m, fileName=file_name)) == UNSUPPORTED


# -- readAllPrograms (2.6.15) and searchFile (2.6.16) -------------------------------------


@pytest.fixture
def seed_mock(client, machine) -> str:
    """A Mock machine holding the seed's 2.6.15 example: SAMPLE, 1/sample1.nc, 1/1/sample2.nc."""
    m = machine("Mock")
    ok(call(client, "createDir", m, dirName="1"))
    ok(call(client, "createDir", m, dirName="1", dirAtCNC="/1"))
    ok(send(client, m, GCODE, fileName="SAMPLE"))
    ok(send(client, m, GCODE, fileName="sample1.nc", dirAtCNC="1"))
    ok(send(client, m, GCODE, fileName="sample2.nc", dirAtCNC="1/1"))
    return m


def test_read_all_programs_gives_folders_relative_to_the_root_as_the_seed_shows(client,
                                                                                 seed_mock):
    assert call(client, "readAllPrograms", seed_mock) == {"programs": [
        {"dirAtCNC": "/", "fileName": "SAMPLE"},
        {"dirAtCNC": "1", "fileName": "sample1.nc"},
        {"dirAtCNC": "1/1", "fileName": "sample2.nc"},
    ]}


def test_read_all_programs_gives_folders_relative_to_the_requested_folder(client, seed_mock):
    assert call(client, "readAllPrograms", seed_mock, subDir="1") == {"programs": [
        {"dirAtCNC": "/", "fileName": "sample1.nc"},
        {"dirAtCNC": "1", "fileName": "sample2.nc"},
    ]}


def test_read_all_programs_on_fanuc_gives_listing_names(client, machine):
    m = machine("Fanuc 0i-F")
    ok(send(client, m, fanuc("0010")))
    assert call(client, "readAllPrograms", m) == {
        "programs": [{"dirAtCNC": "/", "fileName": "10"}]}


@pytest.mark.parametrize(("model", "file_name", "content"), [
    ("Fanuc 0i-F", None, fanuc("0010")), ("Fanuc 18i", None, fanuc("0010")),
    ("Siemens 840D", "PART.MPF", GCODE), ("Heidenhain TNC640", "PART.h", GCODE),
    ("Mitsubishi M800", "100", GCODE),
])
def test_a_file_read_all_programs_lists_at_the_root_reads_back_by_its_dir_at_cnc(
        client, machine, model, file_name, content):
    m = machine(model)
    ok(send(client, m, content, **({"fileName": file_name} if file_name else {})))
    [listed] = call(client, "readAllPrograms", m)["programs"]

    assert listed["dirAtCNC"] == "/"  # 2.6.15: the requested folder itself
    assert call(client, "receiveFile", m, **listed) == {"content": content,
                                                        "encoding": "us-ascii"}


def test_search_file_returns_the_listing_of_the_folder_holding_the_file(client, seed_mock):
    assert call(client, "searchFile", seed_mock, fileName="sample1.nc") == {
        "dirAtCNC": "/1", "programs": ["sample1.nc"], "subDirs": ["1"]}


def test_search_file_searches_below_the_requested_folder_only(client, seed_mock):
    assert code(call(client, "searchFile", seed_mock, fileName="SAMPLE", subDir="1")) \
        == PATH_NOT_FOUND


def test_search_file_of_a_missing_file_is_path_not_found(client, seed_mock):
    assert code(call(client, "searchFile", seed_mock, fileName="NOPE.nc")) == PATH_NOT_FOUND


# -- extension required (Siemens, Heidenhain) ---------------------------------------------


@pytest.mark.parametrize(("model", "name"), [("Siemens 840D", "PART1"),
                                             ("Heidenhain TNC640", "PLATE")])
def test_send_without_extension_is_a_bad_parameter_where_the_model_needs_one(client, machine,
                                                                            model, name):
    m = machine(model)
    assert code(send(client, m, GCODE, fileName=name)) == BAD_PARAMETER
    assert programs(client, m) == []


@pytest.mark.parametrize(("model", "name"), [("Siemens 840D", "PART1"),
                                             ("Heidenhain TNC640", "PLATE")])
def test_receive_without_extension_is_a_bad_parameter_where_the_model_needs_one(client, machine,
                                                                               model, name):
    m = machine(model)
    ok(send(client, m, GCODE, fileName=f"{name}.MPF"))
    assert code(call(client, "receiveFile", m, fileName=name)) == BAD_PARAMETER


def test_mock_takes_a_name_without_extension(client, machine):
    m = machine("Mock")
    ok(send(client, m, GCODE, fileName="SAMPLE"))
    assert programs(client, m) == ["SAMPLE"]


# -- receiveFile / sendFile bodies (2.6.3, 2.6.6) -------------------------------------------


def test_receive_file_gives_ascii_text_as_content_in_us_ascii(client, machine):
    m = machine("Mock")
    ok(send(client, m, GCODE, fileName="A.nc"))
    assert call(client, "receiveFile", m, fileName="A.nc") == {
        "content": GCODE, "encoding": "us-ascii"}


def test_receive_file_gives_non_ascii_text_in_the_machines_encoding(client, machine):
    m = machine("Mock")
    ok(send(client, m, "(Größe)\nM30\n", fileName="A.nc"))
    assert call(client, "receiveFile", m, fileName="A.nc") == {
        "content": "(Größe)\nM30\n", "encoding": "utf-8"}


def test_receive_file_gives_binary_bytes_as_base64(client, machine):
    m = machine("Mock")
    data = bytes(range(256))
    ok(send_stream(client, m, data, fileName="tool.bin"))
    assert call(client, "receiveFile", m, fileName="tool.bin") == {
        "base64": base64.b64encode(data).decode()}


def test_send_file_with_base64_stores_the_decoded_bytes(client, machine):
    m = machine("Mock")
    data = b"\x00\x01\xfe\xff binary"
    ok(send(client, m, b64=base64.b64encode(data).decode(), fileName="tool.bin"))
    assert receive_stream(client, m, fileName="tool.bin") == data


def test_send_file_takes_base64_broken_into_lines(client, machine):
    m = machine("Mock")
    data = bytes(range(256))  # encodebytes writes 76 characters a line, as MIME does
    ok(send(client, m, b64=base64.encodebytes(data).decode().replace("\n", "\r\n"),
            fileName="tool.bin"))
    assert receive_stream(client, m, fileName="tool.bin") == data


def test_send_file_takes_its_body_fields_in_any_case(client, machine):
    m = machine("Mock")  # as a client's classes write them
    response = client.post("/api/cnc/sendFile", params={"machineID": m, "fileName": "A.nc"},
                           json={"Content": "(Größe)\n", "Encoding": "latin-1"})
    ok(response.json())
    assert receive_stream(client, m, fileName="A.nc") == "(Größe)\n".encode("latin-1")


def test_send_file_content_wins_over_base64(client, machine):
    m = machine("Mock")
    ok(send(client, m, "from content\n", b64=base64.b64encode(b"from base64").decode(),
            fileName="A.nc"))
    assert receive_stream(client, m, fileName="A.nc") == b"from content\n"


@pytest.mark.parametrize(("encoding", "content"), [
    ("utf-8\x00", "x"),  # a NUL in the codec's name
    ("idna", "a..b"),  # a codec that refuses the text by rules of its own (an empty label)
])
def test_content_an_encoding_refuses_is_a_bad_parameter_wherever_it_is_sent(
        client, machine, encoding, content):
    m = machine("Mock")
    body = {"content": content, "encoding": encoding}
    single = client.post("/api/cnc/sendFile", params={"machineID": m, "fileName": "E.nc"},
                         json=body)
    batch = client.post("/api/cnc/batchSendFile",
                        json={**body, "targets": [{"machineID": m, "fileName": "E.nc"}]})
    job = client.post("/api/jobs", json={**body, "kind": "send", "fileName": "E.nc",
                                         "machines": {"ids": [m]}})

    assert (single.status_code, code(single.json())) == (200, BAD_PARAMETER)
    assert [code(r) for r in batch.json()] == [BAD_PARAMETER]  # the target's, in place
    assert job.json()["errorCode"] == BAD_PARAMETER  # a job is refused whole
    assert programs(client, m) == []
    [made] = client.get("/api/jobs").json()  # the batch's, with its failed target
    assert made["id"] == batch.headers["X-Dncq-Job"] and made["state"] == "failed"


def test_send_file_takes_files_up_to_10_mb_and_refuses_more_writing_nothing(client, machine):
    m = machine("Mock")
    limit = 10 * 1024 * 1024  # 2.6.6: sendFileStream is for larger files

    ok(send(client, m, "G" * limit, fileName="AT.nc"))
    over = send(client, m, "G" * (limit + 1), fileName="OVER.nc")

    assert code(over) == 20012 and "sendFileStream" in over["statusMsg"]
    assert programs(client, m) == ["AT.nc"]


def test_send_file_with_invalid_base64_is_a_bad_parameter(client, machine):
    m = machine("Mock")
    assert code(send(client, m, b64="not base64!", fileName="A.bin")) == BAD_PARAMETER
    assert programs(client, m) == []


def test_a_json_body_sent_as_a_form_is_refused_naming_the_content_type_it_needs(client, machine):
    # curl -d without -H 'content-type: application/json': "Input should be a valid
    # dictionary" named neither the header nor the type the body came as.
    m = machine("Mock")
    response = client.post("/api/cnc/sendFile", params={"machineID": m, "fileName": "A.nc"},
                           content=b'{"content": "G0 X0\\n"}',
                           headers={"content-type": "application/x-www-form-urlencoded"})

    assert response.status_code == 400
    said = response.json()
    assert said["errorCode"] == 20001
    assert "Content-Type: application/json" in said["statusMsg"], said
    assert "application/x-www-form-urlencoded" in said["statusMsg"], said
