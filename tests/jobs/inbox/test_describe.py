"""What a received program says of itself: its number or name, and its first comment."""

from __future__ import annotations

import pytest

from jobs.inbox.describe import describe


@pytest.mark.parametrize(("data", "number", "comment"), [
    (b"%\nO0010 (BRACKET)\nG0 X0\nM30\n%\n", "O0010", "BRACKET"),
    (b"O0010(BRACKET)\nM30\n", "O0010", "BRACKET"),
    (b"%\r\n:0010\r\n(ISO TAPE)\r\nM30\r\n%\r\n", "O0010", "ISO TAPE"),
    (b"%\nO00010\n(HAAS PART)\nM30\n%\n", "O0010", "HAAS PART"),
    (b"\x00\x00\x11%\nO12345 ( FIVE DIGITS )\n", "O12345", "FIVE DIGITS"),
    (b"0 BEGIN PGM BRACKET MM\n1 ; ROUGH PASS\n2 END PGM BRACKET MM\n", "BRACKET.H",
     "ROUGH PASS"),
    (b"%BRACKET G71 *\nN10 G00 X0 *\nN99999 %BRACKET G71 *\n", "BRACKET.I", None),
    (b"%_N_BRACKET_MPF\n;$PATH=/_N_MPF_DIR\n; finish pass\nG0 X0\nM30\n", "BRACKET.MPF",
     "finish pass"),
    (b"%MPF123\nG0 X0\n", "MPF123", None),
], ids=["fanuc", "fanuc-no-space", "iso-colon", "haas-five-digits", "tape-noise",
        "heidenhain", "heidenhain-iso", "siemens", "siemens-old"])
def test_the_header_gives_the_number_and_the_first_comment_is_found(
        data: bytes, number: str, comment: str | None) -> None:
    said = describe(data)

    assert (said.program_number, said.comment) == (number, comment)


def test_a_program_without_a_header_has_no_number_but_its_comment() -> None:
    said = describe(b"G21 G90\n()\n(FACE MILL)\nM30\n")

    assert (said.program_number, said.comment) == (None, "FACE MILL")


def test_nothing_at_all_says_nothing() -> None:
    assert describe(b"").program_number is None
    assert describe(b"%\n%\n").comment is None


def test_bytes_of_any_code_page_are_described() -> None:
    said = describe("O0010 (WERKSTÜCK)\n".encode("latin-1"))

    assert said.comment == "WERKSTÜCK"
