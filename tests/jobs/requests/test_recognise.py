"""Recognising requests: header commands, body commands in the request program, patterns,
and text that is not a program refused without an exception."""

from __future__ import annotations

import pytest

from jobs.fleet.request_settings import Action, RequestSettings, resolve
from jobs.requests.recognise import Command, recognise, same_program

SEED = b"O8888\nN0010 (DIR=/VIPROS)\nN0020 (PRG=0010)\n%\n"
ESC_HEADER = {"start": "#1B#26", "end": "#1B#5C", "name_chars": 2, "separator": ""}


def _header(**header: object) -> RequestSettings:
    return RequestSettings(where="header", header={**ESC_HEADER, **header})


def _pairs(text: bytes, settings: RequestSettings) -> list[tuple[str, str]]:
    return [(c.name, c.body) for c in recognise(text, settings).commands]


def test_the_seeds_example_is_a_request_with_its_two_commands_in_order():
    found = recognise(SEED, RequestSettings())

    assert found.is_request
    assert found.program_name == "O8888"
    assert found.commands == [
        Command("DIR", "/VIPROS", Action.SET_PATH, "body", 2),
        Command("PRG", "0010", Action.SEND, "body", 3),
    ]


def test_body_commands_of_a_program_with_another_name_are_not_read():
    found = recognise(b"%\nO0010\n(PRG=0020)\nG0 X0\nM30\n%\n", RequestSettings())

    assert not found.is_request
    assert found.program_name == "O0010"
    assert found.commands == []


def test_the_request_program_is_matched_by_number_not_spelling():
    assert recognise(b"%\n:08888\n(PRG=1)\n%\n", RequestSettings()).is_request


def test_a_program_number_with_five_digits_is_the_haas_request_program():
    assert same_program("O8888", "O08888")
    assert not same_program("O8889", "O08888")


def test_several_programs_in_one_line_of_comments_are_all_read():
    text = b"%\nO8888\n(PRG=111)(PRG=222)\n%\n"

    assert _pairs(text, RequestSettings()) == [("PRG", "111"), ("PRG", "222")]


def test_slash_commands_are_read_one_a_line():
    text = b"%\nO8888\n/REQ 111\n/REQ 222\n%\n"

    assert _pairs(text, RequestSettings()) == [("REQ", "111"), ("REQ", "222")]


def test_slash_commands_on_one_line_are_each_read():
    text = b"%\nO8888\nN10 /REQ 111 /REQ 222\n%\n"

    assert _pairs(text, RequestSettings()) == [("REQ", "111"), ("REQ", "222")]


def test_a_slash_commands_body_may_start_with_a_slash():
    assert _pairs(b"O8888\n/DIR /VIPROS/OLD\n%", RequestSettings()) == [("DIR", "/VIPROS/OLD")]


def test_comment_syntax_alone_does_not_read_slash_words():
    settings = RequestSettings(body_syntax="comment")

    assert _pairs(b"O8888\n/REQ 111\n(PRG=222)\n%", settings) == [("PRG", "222")]


def test_a_slash_inside_a_comment_is_not_a_slash_command():
    assert _pairs(b"O8888\n(DIR= /VIPROS)\n%", RequestSettings()) == [("DIR", "/VIPROS")]


def test_a_comment_that_is_a_known_name_alone_is_a_command_without_body():
    assert _pairs(b"O8888\n(DIR=VIPROS)\n(LST)\n%", RequestSettings()) == [
        ("DIR", "VIPROS"), ("LST", "")]


@pytest.mark.parametrize("title", ["REQ", "DEL", "PRG", "FIL"])
def test_a_one_word_title_that_names_a_command_needing_a_body_is_not_a_command(title):
    text = f"O8888 ({title})\n(DIR=VIPROS)\n(PRG=1)\n%".encode()

    assert _pairs(text, RequestSettings()) == [("DIR", "VIPROS"), ("PRG", "1")]


def test_a_plain_comment_of_the_request_program_is_not_a_command():
    assert _pairs(b"O8888 (REQUEST FOR JOB 12)\n(PRG=1)\n%", RequestSettings()) == [("PRG", "1")]


def test_an_unknown_command_is_kept_without_action():
    found = recognise(b"O8888\n(FETCH=0010)\n%", RequestSettings())

    assert found.commands == [Command("FETCH", "0010", None, "body", 2)]


def test_a_siemens_request_program_is_read_with_semicolon_comments():
    text = b"%_N_DNCREQ_MPF\n;$PATH=/_N_MPF_DIR\nN10 ;DIR=VIPROS\nN20 ;PRG=PART1\nM30\n"
    found = recognise(text, resolve("Siemens 840D", None))

    assert found.program_name == "DNCREQ.MPF"
    assert found.is_request
    assert [(c.name, c.body) for c in found.commands] == [("DIR", "VIPROS"), ("PRG", "PART1")]


def test_a_heidenhain_iso_request_program_is_read_without_its_block_end():
    text = b"%9999 G71 *\nN10 ;DIR=VIPROS *\nN20 ;PRG=1234 *\nN99999999 %9999 G71 *\n"
    found = recognise(text, resolve("Heidenhain TNC640", None))

    assert found.program_name == "9999"
    assert [(c.name, c.body) for c in found.commands] == [("DIR", "VIPROS"), ("PRG", "1234")]


def test_a_header_command_between_escape_markers_is_read():
    text = b"\x1b&H=0010\x1b\\\n%\nO0010\nG0 X0\n%\n"
    settings = _header(name_chars=0, separator="=", letters_only=False)

    assert _pairs(text, settings) == [("H", "0010")]


def test_the_first_n_characters_of_a_header_command_are_its_name():
    text = b"\x1b&FW0010\x1b\\\n%\nO0010\n%\n"

    assert _pairs(text, _header(name_chars=2)) == [("FW", "0010")]


def test_letters_only_moves_a_names_trailing_digits_to_the_body():
    text = b"\x1b&H0010\x1b\\\n%\nO0010\n%\n"

    assert _pairs(text, _header(name_chars=2, letters_only=True)) == [("H", "0010")]


def test_without_letters_only_the_first_n_characters_are_the_name_whatever_they_are():
    text = b"\x1b&H0010\x1b\\\n%\nO0010\n%\n"

    assert _pairs(text, _header(name_chars=2)) == [("H0", "010")]


def test_the_separator_is_stripped_from_the_front_of_the_body():
    text = b"\x1b&FW:0010\x1b\\\n%\nO0010\n%\n"

    assert _pairs(text, _header(name_chars=2, separator=":")) == [("FW", "0010")]


def test_what_comes_before_the_start_marker_is_not_a_command():
    text = b"FW0099\x1b&FW0010\x1b\\\n%\nO0010\n%\n"

    assert _pairs(text, _header()) == [("FW", "0010")]


def test_a_header_command_without_end_marker_ends_with_its_line():
    text = b"\x1b&FW0010\n%\nO0010\n%\n"

    assert _pairs(text, _header()) == [("FW", "0010")]


def test_a_header_marker_in_the_program_body_is_not_a_header_command():
    text = b"%\nO0010\n\x1b&FW0010\x1b\\\n%\n"

    assert _pairs(text, _header()) == []


def test_a_header_send_command_makes_a_request_of_any_program():
    text = b"\x1b&PRG=0010\x1b\\\n%\nO0001\n%\n"
    settings = _header(name_chars=0, separator="=")

    assert recognise(text, settings).is_request


def test_a_received_name_header_command_makes_the_request_program_of_its_body():
    text = b"(NAME=O8888)\n%\nO1234\n(PRG=0010)\n%\n"
    found = recognise(text, RequestSettings(where="both"))

    assert found.is_request
    assert [(c.name, c.where) for c in found.commands] == [("NAME", "header"), ("PRG", "body")]


def test_header_only_settings_do_not_read_the_request_programs_body():
    text = b"%\nO8888\n(PRG=0010)\n%\n"

    assert not recognise(text, RequestSettings(where="header")).is_request


def test_a_pattern_with_two_groups_gives_command_and_body():
    settings = RequestSettings(patterns=[r"^N\d+ ([A-Z]+):(\S*)"])
    text = b"O8888\nN10 DIR:VIPROS\nN20 PRG:0010\n%"

    assert [(c.name, c.body, c.where, c.line) for c in recognise(text, settings).commands] == [
        ("DIR", "VIPROS", "pattern", 2), ("PRG", "0010", "pattern", 3)]


def test_patterns_replace_the_comment_syntax():
    settings = RequestSettings(patterns=[r"\[(?P<command>\w+) (?P<body>\w*)\]"])
    text = b"O8888\n(PRG=1111)\n[PRG 2222]\n%"

    assert _pairs(text, settings) == [("PRG", "2222")]


def test_line_numbers_count_cr_lf_and_bare_cr_line_ends():
    text = b"O8888\r\n(DIR=A)\r(PRG=1)\r\n%"

    assert [c.line for c in recognise(text, RequestSettings()).commands] == [2, 3]


def test_tape_leader_and_flow_control_are_not_part_of_the_text():
    text = b"\x00\x00\x00\x11%\nO8888\n(PRG=1\x13)\n%\x00\x00"

    assert _pairs(text, RequestSettings()) == [("PRG", "1")]


@pytest.mark.parametrize(("text", "reason"), [
    (b"%\nO8888\n(PRG=1)\x00\x00junk\n%", "NUL byte at offset"),
    (bytes(range(256)) * 4, "binary data"),
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "binary data"),
    (b"\x00\x00\x00", "empty"),
])
def test_garbage_is_refused_with_a_reason(text, reason):
    found = recognise(text, RequestSettings())

    assert not found.is_request
    assert found.commands == []
    assert reason in (found.refused or "")


def test_latin1_text_from_an_older_control_is_read():
    found = recognise("O8888\n(MSG=Bohrung ä)\n(PRG=1)\n%".encode("latin-1"), RequestSettings())

    assert found.refused is None
    assert [c.name for c in found.commands] == ["MSG", "PRG"]


def test_an_enormous_request_program_is_a_request_refused_as_too_large():
    text = b"%\nO8888\n" + b"(PRG=0010)\n" * 10_000 + b"%\n"
    found = recognise(text, RequestSettings())

    assert found.is_request and not found.commands  # refused, with an answer saying why
    assert found.program_name == "O8888"
    assert "more than the 65,536 a request may have" in (found.refused or "")


def test_a_large_part_program_is_not_searched_but_not_refused():
    text = b"%\nO0010\n" + b"G1 X10 Y10 F200\n" * 10_000 + b"%\n"
    found = recognise(text, RequestSettings())

    assert (found.is_request, found.refused, found.program_name) == (False, None, "O0010")
    assert found.notes and "not searched for requests" in found.notes[0]


def test_a_request_with_too_many_commands_is_refused():
    text = b"O8888\n" + b"(PRG=1)" * 201 + b"\n%"

    assert "at most 200" in (recognise(text, RequestSettings()).refused or "")


def test_the_punch_on_and_off_codes_are_not_part_of_the_text():
    text = b"\x12%\nO8888\n(PRG=1)\n%\x14"

    assert _pairs(text, RequestSettings()) == [("PRG", "1")]


@pytest.mark.parametrize(("first_line", "name"), [
    (b"O0010 (BRACKET)", "O0010"),
    (b"PART1", "PART1"),
    (b"0 BEGIN PGM BRACKET MM", "BRACKET.H"),
    (b"N10 G0 X0", None),  # a block: no name
    (b"G0 X0", None),
    (b"12 G0 X0", None),
    (b"X10.5 Y2", None),
    (b"0 BEGIN PGM ../../EVIL MM", None),
])
def test_a_program_is_named_by_its_number_or_a_plain_word_never_by_a_block(first_line, name):
    # A block's first word named it: unrelated programs were received as N10, G0 or 0000
    # and approved as versions of one another.
    found = recognise(b"%\n" + first_line + b"\nG1 X10 F200\nM30\n%\n", RequestSettings())

    assert (found.is_request, found.program_name) == (False, name)
