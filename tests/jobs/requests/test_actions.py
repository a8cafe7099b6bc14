"""Every action a request may ask for, end to end: the seed's and those beyond it.

Most go through the drop folder of a mock machine (the same executor as the links,
`jobs.requests.handling`, with its answers written as files); the tool-break request goes
over the RS-232 pseudo-terminal of the simulated control. The library, the inbox and the
job records are the real ones on a real database.
"""

from __future__ import annotations

import logging
import re

import pytest

from jobs.db import session_scope
from jobs.fleet.request_presets import COMMANDS
from jobs.inbox import service as inbox
from jobs.library import blobs
from jobs.library import service as library
from jobs.library.models import VersionState
from jobs.requests import drop, memory
from tests.jobs.helpers import wait_until
from tests.jobs.requests.conftest import O0010, request_jobs, wait_for_jobs
from tests.jobs.requests.test_on_links import press_read_when_asked, rs232, stored  # noqa: F401
from tests.worker.transports.serial_lines import serial_machine  # noqa: F401

O0020 = "%\nO0020 (FLANGE)\nG0 X0\nM30\n%\n"


def request(*lines: str) -> bytes:
    """The request program `O8888` with these lines."""
    return ("%\nO8888\n" + "\n".join(lines) + "\n%\n").encode()


def comments(program: bytes) -> list[str]:
    """The texts of a program's comment blocks, in order."""
    return re.findall(r"^(?:N\d+ )?\((.*)\)$", program.decode(), re.MULTILINE)


def the_job(settings) -> dict:
    [job] = request_jobs(settings)
    return job


def approved_bytes(settings, folder: str, name: str) -> bytes:
    with session_scope(settings.resolved_database_url) as session:
        chosen = library.approved(library.find(session=session, folder=folder, name=name))
        assert chosen is not None
        sha = chosen.sha256
    return blobs.read_all(settings, sha)


def inbox_items(settings, machine_id: str = "m1") -> list:
    with session_scope(settings.resolved_database_url) as session:
        items = inbox.list_items(session=session, machine_id=machine_id)
        session.expunge_all()
    return items


def test_the_fanuc_presets_command_names_are_the_ones_these_tests_use() -> None:
    assert {name: COMMANDS[name] for name in (
        "PRG", "REQ", "LST", "DIR", "FIL", "NAME", "DEL", "REN", "MSG", "TOOLBREAK", "CMP",
        "RCVDIR")} == {
        "PRG": "send", "REQ": "send", "LST": "list", "DIR": "set_path", "FIL": "set_file",
        "NAME": "received_name", "DEL": "delete", "REN": "rename", "MSG": "skip",
        "TOOLBREAK": "toolbreak", "CMP": "compare", "RCVDIR": "directory"}


# -- the seed's actions ----------------------------------------------------------------


def test_send_answers_the_library_programs_bytes(settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(PRG=10)"))  # padded to 0010

    machine.scan()

    assert machine.read("O0010") == O0010.encode()
    assert the_job(settings)["targets"][0]["statusMsg"] == "sent library VIPROS/0010"


def test_list_answers_the_folders_programs_one_line_each_between_header_and_footer(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    add_program("VIPROS", "0020", O0020)
    add_program("OTHER", "0030", "%\nO0030\nM30\n%\n")
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(LST=)"))

    machine.scan()

    listing = machine.read("O8889")
    assert listing.decode().splitlines()[:2] == ["%", "O8889"]
    assert listing.decode().splitlines()[-2:] == ["M30", "%"]
    header, first, second, footer = comments(listing)
    assert (header, footer) == ("VIPROS: 2 FILES", "END OF LIST")
    assert re.fullmatch(rf"0010 {len(O0010)} \d{{4}}-\d\d-\d\d \d\d:\d\d UTC", first)
    assert re.fullmatch(rf"0020 {len(O0020)} \d{{4}}-\d\d-\d\d \d\d:\d\d UTC", second)
    assert the_job(settings)["targets"][0]["statusMsg"] == "listed 2 programs of VIPROS"


def test_a_library_program_is_found_however_its_folder_and_name_are_cased(
        settings, drop_machine, add_program) -> None:
    """A Fanuc's keys are capitals: a program kept as `Vipros/Bracket.nc` is asked for as
    VIPROS/BRACKET.NC, as the seed's DNC server found it in a Windows folder."""
    add_program("Vipros", "Bracket.nc", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(PRG=BRACKET.NC)", "(LST=)"))

    machine.scan()

    assert machine.read("O0010") == O0010.encode()
    assert "BRACKET.NC" in " ".join(comments(machine.read("O8889")))  # in capitals
    sent, listed = the_job(settings)["targets"]
    assert sent["statusMsg"] == "sent library Vipros/Bracket.nc"
    assert listed["statusMsg"] == "listed 1 programs of VIPROS"


def test_set_path_takes_a_folder_below_the_source_folder(
        settings, drop_machine, add_program) -> None:
    add_program("SHOP/VIPROS/OLD", "0010", O0010)
    add_program("VIPROS/OLD", "0010", O0020)  # outside the source: never sent
    machine = drop_machine(sources=["library:SHOP"])
    machine.drop("O8888", request("(DIR=\\VIPROS\\OLD)", "(PRG=0010)"))

    machine.scan()

    assert machine.read("O0010") == O0010.encode()
    [target] = the_job(settings)["targets"]
    assert (target["folder"], target["statusMsg"]) == ("VIPROS/OLD",
                                                      "sent library SHOP/VIPROS/OLD/0010")


def test_a_set_path_that_leaves_the_sources_refuses_the_request_and_reads_nothing(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine(sources=["library:VIPROS"])
    machine.drop("O8888", request("(DIR=../VIPROS)", "(PRG=0010)"))

    machine.scan()

    assert machine.names() == ["O8890"]
    said = " ".join(comments(machine.read("O8890")))  # a long reason is wrapped
    assert said.startswith("REFUSED: DIR=../VIPROS") and "LEAVES THE SOURCES" in said
    job = the_job(settings)
    assert job["state"] == "failed" and job["targets"][0]["action"] == "none"


def test_skip_is_logged_and_the_rest_of_the_request_still_runs(
        settings, drop_machine, add_program, caplog) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(MSG=CALL JOE)", "(DIR=/VIPROS)", "(PRG=0010)"))

    with caplog.at_level(logging.INFO, logger="jobs.requests.handling"):
        machine.scan()

    assert "machine m1 request: skipped MSG=CALL JOE (body, line 3)" in caplog.messages
    [target] = the_job(settings)["targets"]  # no target of its own: a note in the record
    assert target["action"] == "send"
    assert target["notes"] == ["skipped MSG=CALL JOE (body, line 3)"]
    assert machine.names() == ["O0010"]


def test_a_request_of_only_skipped_commands_is_answered_that_nothing_ran(
        settings, drop_machine) -> None:
    machine = drop_machine()
    machine.drop("O8888", request("(MSG=CALL JOE)"))

    machine.scan()

    assert comments(machine.read("O8890")) == ["REFUSED: THE REQUEST HAS NO COMMAND DNCQ RUNS"]


def test_set_file_as_the_last_command_sends_the_file(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(FIL=0010)", "(MSG=THANKS)"))

    machine.scan()

    assert machine.read("O0010") == O0010.encode()
    [target] = the_job(settings)["targets"]
    assert (target["action"], target["fileName"]) == ("send", "0010")


def test_received_name_in_the_header_names_the_program_in_the_inbox(
        settings, drop_machine) -> None:
    machine = drop_machine(where="both")
    machine.drop("PUNCH", b"(NAME=O77)\n%\nO1234 (MY PART)\nG0 X0\nM30\n%\n")

    machine.scan()

    [item] = inbox_items(settings)
    assert (item.name, item.program_number, item.state.value) == ("0077", "O1234", "pending")
    assert machine.names() == []


def test_delete_takes_the_program_out_of_the_library_and_reports_it(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(DEL=0010)"))

    machine.scan()

    assert comments(machine.read("O8890")) == ["DELETED: VIPROS/0010"]
    with session_scope(settings.resolved_database_url) as session:
        assert library.list_programs(session=session, folder="VIPROS") == []
        assert library.find(session=session, folder="VIPROS", name="0010", deleted=True)
    assert the_job(settings)["targets"][0]["statusMsg"] == "deleted library VIPROS/0010"


@pytest.mark.parametrize("commands", [("(DEL=0010)",), ("(FIL=0010)", "(REN=0030)")])
def test_a_program_with_no_approved_version_is_not_found_to_delete_or_rename_and_kept(
        settings, drop_machine, add_program, commands: tuple[str, ...]) -> None:
    # The operator can neither list nor be sent it: it is not there for him to change.
    add_program("VIPROS", "0010", O0010, approve=False)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", *commands))

    machine.scan()

    assert comments(machine.read("O8890")) == ["NOT FOUND: VIPROS/0010"]
    with session_scope(settings.resolved_database_url) as session:
        assert [p.name for p in library.list_programs(session=session, folder="VIPROS")] == [
            "0010"]


def test_rename_moves_the_program_to_its_new_name_and_reports_it(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(FIL=0010)", "(REN=0030)"))

    machine.scan()

    assert comments(machine.read("O8890")) == ["RENAMED: VIPROS/0010 TO 0030"]
    with session_scope(settings.resolved_database_url) as session:
        assert [p.name for p in library.list_programs(session=session, folder="VIPROS")] == [
            "0030"]
    assert approved_bytes(settings, "VIPROS", "0030") == O0010.encode()
    [target] = the_job(settings)["targets"]
    assert (target["action"], target["fileName"], target["newName"]) == ("rename", "0010",
                                                                         "0030")


def test_a_renamed_program_keeps_its_version_waiting_for_review(
        settings, drop_machine, add_program) -> None:
    # A programmer's newer version, not yet approved, must not be lost to a rename typed
    # at the control: it waits under the new name, the approved one still what is sent.
    add_program("VIPROS", "0010", O0010)
    edited = O0010.replace("G0 X0", "G0 X5")
    add_program("VIPROS", "0010", edited, approve=False)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(FIL=0010)", "(REN=0030)"))

    machine.scan()

    assert comments(machine.read("O8890")) == ["RENAMED: VIPROS/0010 TO 0030"]
    assert approved_bytes(settings, "VIPROS", "0030") == O0010.encode()
    with session_scope(settings.resolved_database_url) as session:
        renamed = library.find(session=session, folder="VIPROS", name="0030")
        [waiting] = [v for v in renamed.versions if v.state is VersionState.PENDING]
        sha = waiting.sha256
    assert blobs.read_all(settings, sha) == edited.encode()


def test_rename_onto_a_program_that_exists_is_refused_and_changes_nothing(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    add_program("VIPROS", "0030", O0020)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(FIL=0010)", "(REN=0030)"))

    machine.scan()

    [said] = comments(machine.read("O8890"))
    assert said.startswith("FAILED: VIPROS/0010: EXISTS")
    assert approved_bytes(settings, "VIPROS", "0010") == O0010.encode()
    assert approved_bytes(settings, "VIPROS", "0030") == O0020.encode()


def test_rename_onto_a_program_of_that_name_in_another_case_is_refused(
        settings, drop_machine, add_program) -> None:
    # Two programs that differ in case only: a request in any other case found neither.
    add_program("VIPROS", "0010", O0010)
    add_program("VIPROS", "PART.NC", O0020)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(FIL=0010)", "(REN=part.nc)"))

    machine.scan()

    [said] = comments(machine.read("O8890"))
    assert said.startswith("FAILED: VIPROS/0010: EXISTS"), said
    with session_scope(settings.resolved_database_url) as session:
        assert [p.name for p in library.list_programs(session=session, folder="VIPROS")] == [
            "0010", "PART.NC"]


# -- sources ---------------------------------------------------------------------------


def test_a_folder_on_another_machine_is_a_source_and_the_first_match_wins(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0020)
    shop = drop_machine("m2", enabled=False, folders=("/NC",))
    shop.drop("0010", O0010.encode(), "/NC")
    machine = drop_machine(sources=["machine:m2:/NC", "library:VIPROS"])
    machine.drop("O8888", request("(PRG=0010)"))

    machine.scan()

    assert machine.read("O0010") == O0010.encode()
    assert the_job(settings)["targets"][0]["statusMsg"] == "sent machine m2 /NC/0010"


def test_a_program_the_first_source_lacks_comes_from_the_next(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0020", O0020)
    drop_machine("m2", enabled=False, folders=("/NC",))
    machine = drop_machine(sources=["machine:m2:/NC", "library:VIPROS"])
    machine.drop("O8888", request("(PRG=0020)"))

    machine.scan()

    assert machine.read("O0020") == O0020.encode()
    assert the_job(settings)["targets"][0]["statusMsg"] == "sent library VIPROS/0020"


def test_a_folder_on_the_requesting_machine_itself_is_read_under_the_lease_the_scan_holds(
        settings, drop_machine) -> None:
    machine = drop_machine(sources=["machine:m1:/NC"], folders=("/NC",))
    machine.drop("0010", O0010.encode(), "/NC")
    machine.drop("O8888", request("(PRG=0010)"))

    machine.scan()  # it used to wait 30 s for a slot of its own machine, then fail

    assert machine.read("O0010") == O0010.encode()
    assert the_job(settings)["targets"][0]["statusMsg"] == "sent machine m1 /NC/0010"


# -- beyond the seed -------------------------------------------------------------------


def test_several_programs_in_one_request_are_each_answered(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    add_program("VIPROS", "0020", O0020)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)(PRG=0010)(PRG=0020)"))

    machine.scan()

    assert machine.names() == ["O0010", "O0020"]
    job = the_job(settings)
    assert [t["answer"] for t in job["targets"]] == ["O0010", "O0020"]
    assert job["state"] == "succeeded"


def test_slash_requests_on_one_line_are_each_answered(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0111", "%\nO0111\nM30\n%\n")
    add_program("VIPROS", "0222", "%\nO0222\nM30\n%\n")
    machine = drop_machine()
    machine.drop("O8888", request("/DIR VIPROS", "/REQ 111 /REQ 222"))

    machine.scan()

    assert machine.names() == ["O0111", "O0222"]
    assert [t["fileName"] for t in the_job(settings)["targets"]] == ["0111", "0222"]


def test_one_missing_program_of_several_is_answered_by_an_error_and_the_others_sent(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)(PRG=0099)(PRG=0010)"))

    machine.scan()

    assert machine.names() == ["O0010", "O8890"]
    assert comments(machine.read("O8890")) == ["NOT FOUND: VIPROS/0099"]
    assert [t["state"] for t in the_job(settings)["targets"]] == ["failed", "succeeded"]


def test_a_tool_break_request_over_rs232_gets_the_program_restarted_from_the_block(
        settings, rs232, add_program) -> None:  # noqa: F811
    add_program("VIPROS", "0010", O0010)
    line = rs232()
    operator = press_read_when_asked(settings, line.control)
    line.punch_text(b"%\nO8888\n(DIR=/VIPROS)\n(TOOLBREAK=N120)(PRG=0010)\n%\n")

    [job] = wait_for_jobs(settings, 1)
    operator.join(10)
    assert job["state"] == "succeeded", job
    [target] = job["targets"]
    assert target["restartBlock"] == "N120"
    assert target["statusMsg"] == "sent library VIPROS/0010 restarted from N120"
    got = stored(line.control, "O0010")
    assert got is not None
    blocks = [x.strip() for x in got.decode().splitlines() if x.strip().strip("%")]
    assert blocks[0] == "O0010 (VIPROS BRACKET)"
    restart_at = blocks.index("N120 Y30.")
    header = blocks[1:restart_at]
    for needed in ("G54", "G90", "T01 M6", "G43 H01", "S2500 M3", "F600"):
        assert needed in header, header
    assert not any(b.startswith(("N100", "N110")) for b in blocks)
    assert blocks[restart_at:] == ["N120 Y30.", "N130 X0", "N140 Y0", "G0 Z50.", "M30"]
    # The line of N120 in the program as stored, as `dncq run --from N120` names it.
    assert f"(RESTART AT LINE {O0010.splitlines().index('N120 Y30.') + 1} N120)" in header


def test_a_tool_break_restarts_a_program_whose_lines_end_in_cr_as_a_run_numbers_them(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010.replace("\n", "\r"))
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)(TOOLBREAK=N120)(PRG=0010)"))

    machine.scan()

    assert machine.names() == ["O0010"]
    blocks = [x for x in machine.read("O0010").decode().splitlines() if x.strip("%")]
    assert blocks[-5:] == ["N120 Y30.", "N130 X0", "N140 Y0", "G0 Z50.", "M30"]
    assert f"(RESTART AT LINE {O0010.splitlines().index('N120 Y30.') + 1} N120)" in blocks


def test_a_tool_break_at_a_block_the_program_lacks_is_answered_with_an_error(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)(TOOLBREAK=N999)(PRG=0010)"))

    machine.scan()

    assert machine.names() == ["O8890"]
    [said, *_] = comments(machine.read("O8890"))
    assert said.startswith("FAILED: VIPROS/0010: CANNOT RESTART VIPROS/0010 FROM N999")
    assert the_job(settings)["targets"][0]["errorCode"] == 20001


def test_a_compare_request_answers_the_differing_blocks_and_stores_nothing(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)(CMP=0010)"))
    machine.scan()
    [asked] = request_jobs(settings)
    assert asked["targets"][0]["statusMsg"] == ("the next program received is compared "
                                                "with VIPROS/0010")
    assert machine.names() == []  # nothing to answer yet

    machine.drop("O0010", O0010.replace("N130 X0", "N130 X1.").encode())
    machine.scan()

    assert machine.names() == ["O8890"]
    assert comments(machine.read("O8890")) == [
        "DIFFERS FROM VIPROS/0010: 1 BLOCKS", "DNC: N130 X0", "CNC: N130 X1."]
    assert inbox_items(settings) == []
    assert approved_bytes(settings, "VIPROS", "0010") == O0010.encode()
    compared = request_jobs(settings)[1]
    assert compared["targets"][0]["action"] == "compare" and compared["state"] == "succeeded"


def test_a_compare_is_for_one_program_the_next_is_received(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)(CMP=0010)"))
    machine.scan()
    machine.drop("O0010", O0010.encode())
    machine.scan()

    assert comments(machine.read("O8890")) == ["SAME AS VIPROS/0010"]
    machine.drop("O0010", O0010.encode())
    machine.scan()

    [item] = inbox_items(settings)
    assert item.name == "0010"


def test_a_directory_runner_sends_the_programs_received_after_it_to_its_folder(
        settings, drop_machine) -> None:
    machine = drop_machine()
    machine.drop("O8888", request("(RCVDIR=JOB42)"))
    machine.scan()
    machine.drop("O1234", b"%\nO1234 (OP10)\nM30\n%\n")
    machine.drop("O1235", b"%\nO1235 (OP20)\nM30\n%\n")
    machine.scan()

    items = inbox_items(settings)
    assert sorted((i.name, i.folder) for i in items) == [("1234", "RECEIVED/JOB42"),
                                                         ("1235", "RECEIVED/JOB42")]
    assert request_jobs(settings)[0]["targets"][0]["action"] == "directory"


def test_after_a_directory_runner_expires_programs_go_to_the_receive_folder(
        settings, drop_machine) -> None:
    machine = drop_machine(directory_expires_s=0.5)
    machine.drop("O8888", request("(RCVDIR=JOB42)"))
    machine.scan()
    wait_until(lambda: memory.get(settings, "m1", "directory") is None, timeout_s=10)

    machine.drop("O1234", b"%\nO1234 (OP10)\nM30\n%\n")
    machine.scan()

    [item] = inbox_items(settings)
    assert item.folder == "RECEIVED"


# -- the inbox and the library -----------------------------------------------------------


def test_a_received_program_never_replaces_the_approved_one_a_request_gets(
        settings, drop_machine, add_program) -> None:
    old = "%\nO1234 (OLD)\nG0 X0\nM30\n%\n"
    add_program("RECEIVED", "1234", old)
    machine = drop_machine()
    machine.drop("O1234", b"%\nO1234 (EDITED)\nG0 X5.\nM30\n%\n")
    machine.scan()

    machine.drop("O8888", request("(DIR=/RECEIVED)(PRG=1234)"))
    machine.scan()

    assert machine.read("O1234") == old.encode()
    with session_scope(settings.resolved_database_url) as session:
        [program] = library.list_programs(session=session, folder="RECEIVED")
        assert [v.number for v in program.versions] == [1]
    [item] = inbox_items(settings)
    assert item.state.value == "pending"


def test_approving_a_received_program_keeps_the_previous_version_and_answers_the_new(
        settings, drop_machine, add_program) -> None:
    old, new = "%\nO1234 (OLD)\nG0 X0\nM30\n%\n", b"%\nO1234 (EDITED)\nG0 X5.\nM30\n%\n"
    add_program("RECEIVED", "1234", old)
    machine = drop_machine()
    machine.drop("O1234", new)
    machine.scan()
    [item] = inbox_items(settings)
    with session_scope(settings.resolved_database_url) as session:
        assert "+G0 X5." in inbox.diff(session=session, settings=settings, item_id=item.id)
        inbox.approve(session=session, settings=settings, item_id=item.id, decided_by="ann")

    machine.drop("O8888", request("(DIR=/RECEIVED)(PRG=1234)"))
    machine.scan()

    assert machine.read("O1234") == new
    with session_scope(settings.resolved_database_url) as session:
        program = library.find(session=session, folder="RECEIVED", name="1234")
        assert [v.number for v in program.versions] == [1, 2]
        first = library.version(session=session, folder="RECEIVED", name="1234", number=1)
        assert first.state is VersionState.APPROVED  # kept, one restore away
        sha = first.sha256
    assert blobs.read_all(settings, sha) == old.encode()


# -- what is refused -------------------------------------------------------------------


def test_garbage_dropped_is_kept_as_a_failed_reception_and_removed(
        settings, drop_machine) -> None:
    machine = drop_machine()
    machine.drop("JUNK", b"\x00\x01\x02\xff\xfe binary \x00\x00")

    assert machine.scan() == 1

    assert machine.names() == []
    [item] = inbox_items(settings)
    assert item.state.value == "failed" and "not a program" in item.reason
    assert the_job(settings)["state"] == "failed"
    with session_scope(settings.resolved_database_url) as session:
        assert library.list_programs(session=session) == []


def test_an_enormous_request_program_is_refused_with_an_answer_saying_why(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    padding = "(PADDING)\n" * 10_000  # 100 KB, over the 64 KB a request may have
    machine.drop("O8888", request("(DIR=/VIPROS)(PRG=0010)", padding))

    machine.scan()

    assert machine.names() == ["O8890"]  # nothing of it was run
    assert "REFUSED: THE REQUEST PROGRAM O8888 IS" in " ".join(comments(machine.read("O8890")))
    assert the_job(settings)["state"] == "failed"


def test_a_request_of_too_many_commands_is_refused(settings, drop_machine) -> None:
    machine = drop_machine()
    machine.drop("O8888", request(*["(MSG=X)"] * 201))

    machine.scan()

    assert "THE REQUEST HAS 201 COMMANDS" in " ".join(comments(machine.read("O8890")))
    assert the_job(settings)["targets"][0]["errorCode"] == 20001


def test_a_file_too_large_to_read_is_kept_as_a_failed_reception_and_removed(
        settings, drop_machine) -> None:
    machine = drop_machine()
    machine.drop("HUGE", b"G1 X1\n" * (drop.MAX_DROPPED_BYTES // 6 + 1))

    machine.scan()

    assert machine.names() == []
    [item] = inbox_items(settings)
    assert item.state.value == "failed" and "HUGE is over" in item.reason


def test_other_machines_requests_are_answered_beside_garbage_and_enormous_ones(
        settings, drop_machine, add_program) -> None:
    add_program("VIPROS", "0010", O0010)
    junk, big, good = drop_machine("m1"), drop_machine("m2"), drop_machine("m3")
    junk.drop("JUNK", b"\x00\x01garbage\x00")
    big.drop("O8888", request("(PRG=0010)", "(PADDING)\n" * 10_000))
    good.drop("O8888", request("(DIR=/VIPROS)(PRG=0010)"))

    assert drop.scan(settings=settings) == 3

    assert good.read("O0010") == O0010.encode()
    assert junk.names() == [] and big.names() == ["O8890"]  # refused, saying why
    states = {j["targets"][0]["machineID"]: j["state"] for j in request_jobs(settings)}
    assert states == {"m1": "failed", "m2": "failed", "m3": "succeeded"}


def test_a_rename_onto_its_own_name_keeps_the_program(
        settings, drop_machine, add_program) -> None:
    # `(FIL=0010)(REN=0010)`, or `(REN=10)` padded to the same name: nothing to move, and
    # the program stays, no longer taken out of the library as the "old" name.
    add_program("VIPROS", "0010", O0010)
    machine = drop_machine()
    machine.drop("O8888", request("(DIR=/VIPROS)", "(FIL=0010)", "(REN=10)"))

    machine.scan()

    assert comments(machine.read("O8890")) == ["RENAMED: VIPROS/0010 TO 0010"]
    assert approved_bytes(settings, "VIPROS", "0010") == O0010.encode()
