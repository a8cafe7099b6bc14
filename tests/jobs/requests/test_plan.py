"""The plan of a request: the seed's commands run in order, and what the commercial tools
added (several programs, tool break, compare, directory runner)."""

from __future__ import annotations

import pytest

from jobs.fleet.request_settings import Action, RequestSettings, resolve
from jobs.requests.answers import ReportKind, error_program, report_line
from jobs.requests.plan import Step, plan

SEED = b"O8888\nN0010 (DIR=/VIPROS)\nN0020 (PRG=0010)\n%\n"


def _request(*commands: str, settings: RequestSettings | None = None):
    text = "%\nO8888\n" + "\n".join(commands) + "\n%\n"
    return plan(text.encode(), settings or RequestSettings())


def _steps(*commands: str, settings: RequestSettings | None = None) -> list[tuple]:
    return [(s.action, s.folder, s.name, s.new_name, s.restart_block)
            for s in _request(*commands, settings=settings).steps]


def test_the_seeds_example_with_the_fanuc_preset_sends_vipros_0010():
    result = plan(SEED, resolve("Fanuc 0i-F", None))

    assert result.is_request and result.refused is None
    assert result.steps == [Step(Action.SEND, "VIPROS", "0010", note="PRG=0010, line 3")]


def test_the_seeds_example_works_with_the_defaults():
    assert [(s.action, s.folder, s.name) for s in plan(SEED, RequestSettings()).steps] == [
        (Action.SEND, "VIPROS", "0010")]


def test_a_send_without_set_path_is_from_the_top_of_the_sources():
    assert _steps("(PRG=10)") == [(Action.SEND, "", "0010", None, None)]


def test_set_path_is_relative_to_the_sources_not_to_the_previous_path():
    assert _steps("(DIR=A)", "(DIR=B)", "(PRG=1)") == [(Action.SEND, "B", "0001", None, None)]


def test_a_list_lists_the_current_folder():
    assert _steps("(DIR=VIPROS)", "(LST=)") == [(Action.LIST, "VIPROS", None, None, None)]


def test_a_list_with_a_body_lists_that_folder():
    assert _steps("(LST=/VIPROS/OLD)") == [(Action.LIST, "VIPROS/OLD", None, None, None)]


def test_a_skipped_command_is_logged_and_not_run():
    result = _request("(MSG=CALL JOE)", "(PRG=1)")

    assert [s.action for s in result.steps] == [Action.SEND]
    assert result.log == ["skipped MSG=CALL JOE (body, line 3)"]


def test_an_unknown_command_is_logged_and_not_run():
    result = _request("(FETCH=1)", "(PRG=1)")

    assert [s.action for s in result.steps] == [Action.SEND]
    assert result.log == ["unknown command FETCH=1 (body, line 3): not run"]


def test_set_file_as_the_last_command_sends_the_file():
    assert _steps("(DIR=VIPROS)", "(FIL=10)") == [(Action.SEND, "VIPROS", "0010", None, None)]


def test_set_file_followed_by_skipped_commands_is_still_the_last_and_sends():
    assert _steps("(FIL=10)", "(MSG=HI)") == [(Action.SEND, "", "0010", None, None)]


def test_set_file_then_rename_renames_the_remembered_file():
    assert _steps("(DIR=VIPROS)", "(FIL=10)", "(REN=20)") == [
        (Action.RENAME, "VIPROS", "0010", "0020", None)]


def test_a_rename_without_a_file_set_refuses_the_request():
    result = _request("(REN=20)")

    assert result.steps == []
    assert "no file to rename" in (result.refused or "")


def test_a_delete_deletes_the_named_file_in_the_current_folder():
    assert _steps("(DIR=VIPROS)", "(DEL=10)") == [(Action.DELETE, "VIPROS", "0010", None, None)]


def test_a_delete_without_a_body_deletes_the_remembered_file():
    assert _steps("(DIR=A)", "(FIL=10)", "(DIR=B)", "(DEL=)") == [
        (Action.DELETE, "A", "0010", None, None)]


def test_received_name_names_a_program_that_is_not_a_request():
    result = plan(b"(NAME=O0077)\n%\nO0010\nG0 X0\n%\n", RequestSettings(where="both"))

    assert not result.is_request
    assert result.received_name == "0077"


def test_a_program_that_is_not_a_request_is_received_under_its_own_name():
    result = plan(b"%\nO0012 (BRACKET)\nG0 X0\nM30\n%\n", RequestSettings())

    assert (result.is_request, result.received_name, result.steps) == (False, "0012", [])


def test_a_siemens_program_is_received_under_its_file_name():
    result = plan(b"%_N_PART1_MPF\nG0 X0\nM30\n", resolve("Siemens 840D", None))

    assert result.received_name == "PART1.MPF"


def test_a_program_without_a_name_is_received_without_one():
    result = plan(b"%\n(JUST A COMMENT)\n%\n", RequestSettings())

    assert (result.is_request, result.received_name) == (False, None)


def test_two_comments_on_a_line_send_two_programs():
    assert _steps("(PRG=111)(PRG=222)") == [(Action.SEND, "", "0111", None, None),
                                            (Action.SEND, "", "0222", None, None)]


def test_two_slash_requests_send_two_programs():
    assert _steps("/REQ 111", "/REQ 222") == [(Action.SEND, "", "0111", None, None),
                                              (Action.SEND, "", "0222", None, None)]


def test_a_tool_break_restarts_the_next_program_sent_from_its_block():
    assert _steps("(TOOLBREAK=N100)(PRG=0010)") == [(Action.SEND, "", "0010", None, "N100")]


def test_a_tool_break_applies_to_the_next_send_only():
    assert _steps("(TOOLBREAK=100)", "(PRG=1)", "(PRG=2)") == [
        (Action.SEND, "", "0001", None, "N100"), (Action.SEND, "", "0002", None, None)]


def test_a_tool_break_may_name_a_tool():
    assert _steps("(TOOLBREAK=T7)(PRG=1)") == [(Action.SEND, "", "0001", None, "T7")]


def test_a_tool_break_without_a_program_after_it_refuses_the_request():
    result = _request("(PRG=1)", "(TOOLBREAK=N100)")

    assert result.steps == []
    assert "no program to send follows it" in (result.refused or "")


def test_a_tool_break_that_is_not_a_block_refuses_the_request():
    assert "is not a block" in (_request("(TOOLBREAK=X1)(PRG=1)").refused or "")


def test_a_compare_names_the_file_the_next_program_is_compared_with():
    assert _steps("(DIR=VIPROS)", "(CMP=10)") == [(Action.COMPARE, "VIPROS", "0010", None, None)]


def test_a_compare_without_a_body_compares_with_the_file_of_the_programs_name():
    assert _steps("(CMP=)") == [(Action.COMPARE, "", None, None, None)]


def test_a_directory_runner_names_its_library_folder():
    assert _steps("(RCVDIR=JOBS/J42)") == [(Action.DIRECTORY, "JOBS/J42", None, None, None)]


def test_a_directory_runner_without_a_folder_refuses_the_request():
    assert "name the library folder" in (_request("(RCVDIR=)").refused or "")


@pytest.mark.parametrize("command", ["(DIR=../..)", "(DIR=C:\\NC)", "(PRG=../x)",
                                     "(LST=/../x)", "(RCVDIR=..)", "(FIL=a/b)"])
def test_a_path_escape_refuses_the_whole_request(command):
    result = _request("(PRG=1)", command, "(PRG=2)")

    assert result.is_request
    assert result.steps == []
    assert result.refused and command[1:-1] in result.refused


@pytest.mark.parametrize("command", ["(PRG=" + "A" * 3000 + ")", "(DIR=" + "../" * 1000 + ")"],
                         ids=["name", "folder"])
def test_a_refusal_of_a_long_command_quotes_it_cut_and_shows_why_within_the_report(command):
    # The text was quoted whole: 50 lines and more, the reason on the last, past max_lines.
    settings = RequestSettings()
    reason = _request(command).refused or ""

    report = error_program(report_line(ReportKind.REFUSED, settings, reason=reason),
                           settings).decode().splitlines()

    assert "..." in reason and len(reason) < 200
    assert len(report) <= settings.error_program.max_lines
    assert report[-3].endswith(("CHARACTERS)", "SOURCES ?'..'?)"))


def test_a_request_of_only_skipped_commands_is_refused_as_having_nothing_to_run():
    assert _request("(MSG=HELLO)").refused == "the request has no command dncq runs"


@pytest.mark.parametrize("text", [b"\x00\xff" * 100, bytes(range(256)), b""])
def test_garbage_gives_a_refused_plan_not_an_exception(text):
    result = plan(text, RequestSettings())

    assert (result.is_request, result.steps) == (False, [])
    assert result.refused


def test_an_enormous_request_is_refused_without_steps():
    result = plan(b"O8888\n" + b"(PRG=1)\n" * 20_000 + b"%", RequestSettings())

    assert (result.is_request, result.steps) == (True, [])
    assert "a request may have" in (result.refused or "")
