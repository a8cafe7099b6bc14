"""The programs sent back: listings, reports and errors a control can read and show."""

from __future__ import annotations

from datetime import datetime
from zoneinfo import ZoneInfo

from jobs.fleet.request_settings import RequestSettings, resolve
from jobs.requests.answers import (
    ListedFile,
    ReportKind,
    compare_lines,
    error_program,
    listing_program,
    report_line,
    report_program,
)

FILES = [ListedFile("0010", 1234, datetime(2024, 3, 5, 14, 7)),
         ListedFile("0020", None, None)]


def test_a_fanuc_listing_is_a_program_of_comments_between_percent_lines():
    text = listing_program("VIPROS", FILES, resolve("Fanuc 0i-F", None))

    assert text == (b"%\n"
                    b"O8889\n"
                    b"(VIPROS: 2 FILES)\n"
                    b"(0010 1234 2024-03-05 14:07 UTC)\n"
                    b"(0020)\n"
                    b"(END OF LIST)\n"
                    b"M30\n"
                    b"%\n")


def test_a_listing_uses_its_templates():
    settings = RequestSettings(listing={
        "header": ["DIR {folder}"], "line": "{name:<6}|{size:>6}|{date}", "footer": [],
        "date_format": "%d.%m.%y", "end_block": ""})

    assert listing_program("A", FILES[:1], settings).splitlines() == [
        b"%", b"O8889", b"(DIR A)", b"(0010  |  1234|05.03.24)", b"%"]


def test_a_listing_writes_its_dates_in_utc_and_says_so():
    berlin = ListedFile("0010", 1234, datetime(2024, 7, 5, 16, 7, tzinfo=ZoneInfo("Europe/Berlin")))
    named = RequestSettings(listing={"date_format": "%d.%m.%y %H:%M %Z"})

    assert b"(0010 1234 2024-07-05 14:07 UTC)" in listing_program("A", [berlin],
                                                                 RequestSettings())
    assert b"(0010 1234 05.07.24 14:07 UTC)" in listing_program("A", [berlin], named)


def test_an_empty_folders_listing_says_so():
    assert b"(NO FILES)" in listing_program("", [], RequestSettings())


def test_the_top_folder_is_listed_as_a_slash():
    assert b"(/: 0 FILES)" in listing_program("", [], RequestSettings())


def test_a_listing_with_block_numbers_numbers_every_block_after_the_name():
    settings = RequestSettings(listing={"block_numbers": True, "block_start": 5,
                                        "block_step": 5, "footer": []})

    assert listing_program("A", FILES[:1], settings).splitlines() == [
        b"%", b"O8889", b"N5 (A: 1 FILES)", b"N10 (0010 1234 2024-03-05 14:07 UTC)", b"N15 M30",
        b"%"]


def test_a_listing_of_more_files_than_allowed_counts_the_rest():
    settings = RequestSettings(listing={"max_files": 1})

    assert b"(AND 1 MORE)" in listing_program("A", FILES, settings)
    assert b"0020" not in listing_program("A", FILES, settings)


def test_a_file_name_with_parentheses_cannot_break_its_comment():
    text = listing_program("A", [ListedFile("X(1)%", 1, None)], RequestSettings())

    assert b"(X?1?? 1)" in text
    assert all(line.count(b"(") == line.count(b")") <= 1 for line in text.splitlines())


def test_a_listing_line_is_cut_to_the_longest_line():
    text = listing_program("A", [ListedFile("N" * 100, 1, None)],
                           RequestSettings(listing={"max_line_chars": 30}))

    assert max(len(line) for line in text.splitlines()) == 30
    assert b"(" + b"N" * 28 + b")" in text


def test_text_is_written_in_capitals_and_printable_ascii():
    text = error_program("Bohrung fräsen\tjetzt \x07", RequestSettings())

    assert b"(BOHRUNG FRASEN JETZT ?)" in text


def test_small_letters_are_kept_when_capitals_are_off():
    assert b"(Missing)" in error_program("Missing", RequestSettings(
        listing={"uppercase": False}))


def test_a_missing_file_gives_the_error_program_the_seed_asks_for():
    settings = resolve("Fanuc 0i-F", None)
    message = report_line(ReportKind.NOT_FOUND, settings, path="VIPROS/0010")

    assert error_program(message, settings) == b"%\nO8890\n(NOT FOUND: VIPROS/0010)\nM30\n%\n"


def test_a_long_error_is_wrapped_into_several_comments():
    settings = RequestSettings(listing={"max_line_chars": 20})
    lines = error_program("NOT FOUND: VIPROS/OLD/0000010", settings).splitlines()

    assert lines[2:4] == [b"(NOT FOUND:)", b"(VIPROS/OLD/0000010)"]
    assert max(len(line) for line in lines) <= 20


def test_delete_and_rename_reports_use_their_templates():
    settings = RequestSettings()
    lines = [report_line(ReportKind.DELETED, settings, path="VIPROS/0010"),
             report_line(ReportKind.RENAMED, settings, path="VIPROS/0020", new_name="0030")]

    assert report_program(lines, settings).splitlines()[2:4] == [
        b"(DELETED: VIPROS/0010)", b"(RENAMED: VIPROS/0020 TO 0030)"]


def test_a_report_longer_than_allowed_ends_with_a_count():
    settings = RequestSettings(error_program={"max_lines": 3})
    lines = report_program([f"LINE {n}" for n in range(10)], settings).splitlines()

    assert lines[2:5] == [b"(LINE 0)", b"(LINE 1)", b"(AND 8 MORE LINES)"]


def test_a_heidenhain_answer_is_framed_as_an_iso_program_with_numbered_blocks():
    settings = resolve("Heidenhain TNC640", None)

    assert error_program("NOT FOUND: A/1234.I", settings) == (
        b"%9997 G71 *\nN10 ;NOT FOUND: A/1234.I *\nN99999999 %9997 G71 *\n")


def test_a_heidenhain_comment_cannot_contain_a_block_end():
    assert b";A?B *" in error_program("A*B", resolve("Heidenhain TNC640", None))


def test_a_siemens_answer_is_a_main_program_with_semicolon_comments():
    settings = resolve("Siemens 840D", None)

    assert error_program("NOT FOUND: A/PART1.MPF", settings) == (
        b"%_N_DNCERR_MPF\n;$PATH=/_N_MPF_DIR\n;NOT FOUND: A/PART1.MPF\nM30\n")


def test_a_haas_answer_carries_its_five_digit_name():
    assert error_program("X", resolve("Haas", None)).splitlines()[:2] == [b"%", b"O08890"]


def test_an_equal_compare_is_reported_the_same():
    settings = RequestSettings()

    assert compare_lines("A/0010", b"%\nO0010\nG0 X0\n%\n", b"O0010\r\nG0 X0  \r\n\r\n",
                         settings) == ["SAME AS A/0010"]


def test_a_differing_compare_reports_the_differing_blocks_of_both():
    lines = compare_lines("A/0010", b"O0010\nG0 X0\nG1 X10\nM30\n",
                          b"O0010\nG0 X0\nG1 X11\nM30\n", RequestSettings())

    assert lines == ["DIFFERS FROM A/0010: 1 BLOCKS", "DNC: G1 X10", "CNC: G1 X11"]
