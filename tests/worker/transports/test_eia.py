"""EIA RS-244 punches decode to ISO text and ISO programs encode to the same punch."""

from __future__ import annotations

import pytest

from worker.transports.eia import EIA_TO_ISO, ISO_TO_EIA, EiaError, decode, encode

# "%", EOB, "O1001", EOB, "G0 X-1.5", EOB, "M30", EOB, "%": hole patterns from the RS-244 table.
PUNCH = bytes([
    0x00, 0x00,  # leader
    0x0B, 0x80,
    0x46, 0x01, 0x20, 0x20, 0x01, 0x80,
    0x67, 0x20, 0x10, 0x37, 0x40, 0x01, 0x6B, 0x15, 0x80,
    0x54, 0x13, 0x20, 0x80,
    0x0B,
    0x00, 0x00,  # trailer
])
TEXT = b"%\nO1001\nG0 X-1.5\nM30\n%"


def test_a_punch_decodes_to_iso_text() -> None:
    assert decode(PUNCH) == TEXT


def test_iso_text_encodes_to_the_punch_without_its_leader() -> None:
    assert encode(TEXT) == PUNCH.strip(b"\x00")


def test_a_program_round_trips_with_crlf_as_one_end_of_block() -> None:
    program = b"%\r\nO0042 (FACE MILL)\r\nG90 G54 G0 X0 Y0\r\nS1200 M3\r\nM30\r\n%"
    assert decode(encode(program)) == program.replace(b"\r\n", b"\n")


def test_every_code_has_odd_parity_and_one_meaning() -> None:
    assert all(bin(code).count("1") % 2 == 1 for code in ISO_TO_EIA.values())
    assert len(EIA_TO_ISO) == len(ISO_TO_EIA)


def test_rubbed_out_codes_are_skipped() -> None:
    assert decode(bytes([0x46, 0x7F, 0x01])) == b"O1"


def test_an_even_parity_code_is_a_parity_error_with_its_offset() -> None:
    with pytest.raises(EiaError, match=r"parity error: 0x03 \(byte 1\)"):
        decode(bytes([0x46, 0x03]))


def test_a_character_eia_lacks_is_refused() -> None:
    with pytest.raises(EiaError, match="'#'"):
        encode(b"#100=1")
