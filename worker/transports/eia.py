"""EIA RS-244 punch code to and from ISO (ASCII) text, for controls that still punch EIA.

An EIA character is one byte, its bits the tape's channels 1 to 8 (bit 0 is channel 1).
Channel 5 is the parity hole: every code has an odd number of holes, except blank tape
(0x00). Channel 8 alone is the end of block (0x80, a line end in ISO); channel 6 alone
is the digit 0; letters have no case (decoded upper case). EIA's end of record (0x0B)
stands for ISO's `%`. Blank tape and DEL (0x7F, a character rubbed out by punching all
holes) are skipped when decoding; an ISO CR is dropped when encoding (one EOB per line).
"""

from __future__ import annotations

from worker.transports.base import Permanent

EIA_EOB = 0x80  # end of block: a line end
EIA_EOR = 0x0B  # end of record (rewind stop): ISO's "%"
EIA_BLANK = 0x00  # tape feed (leader and trailer)
EIA_DELETE = 0x7F  # all seven holes: a rubbed-out character, ignored

# Digits 1..9 are their binary value in channels 1-4; channel 5 makes the holes odd.
_DIGIT_HOLES = [0, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x09]


def _odd(code: int) -> int:
    """`code` with the parity hole (channel 5) punched when its holes are even."""
    return code if bin(code).count("1") % 2 else code | 0x10


def _table() -> dict[str, int]:
    table = {"0": 0x20}
    for digit in range(1, 10):
        table[str(digit)] = _odd(_DIGIT_HOLES[digit])
    for index, letter in enumerate("ABCDEFGHI", start=1):  # channels 6 and 7
        table[letter] = _odd(0x60 | _DIGIT_HOLES[index])
    for index, letter in enumerate("JKLMNOPQR", start=1):  # channel 7
        table[letter] = _odd(0x40 | _DIGIT_HOLES[index])
    for index, letter in enumerate("STUVWXYZ", start=2):  # channel 6, from the 2 pattern
        table[letter] = _odd(0x20 | _DIGIT_HOLES[index])
    table.update({
        " ": 0x10, "\n": EIA_EOB, "%": EIA_EOR, "\t": 0x3E, "\b": 0x2A,
        ".": 0x6B, ",": 0x3B, "+": 0x70, "-": 0x40, "/": 0x31, "&": 0x0E,
        "(": 0x1A,  # control out: a comment starts
        ")": 0x4A,  # control in: the comment ends
    })
    return table


ISO_TO_EIA: dict[str, int] = _table()
EIA_TO_ISO: dict[int, str] = {code: char for char, code in ISO_TO_EIA.items()}
_SKIPPED = frozenset({EIA_BLANK, EIA_DELETE})


class EiaError(Permanent):
    """A program that cannot be punched in EIA, or a punch that is not EIA."""


def encode(text: bytes) -> bytes:
    """ISO program text as EIA codes.

    Raises:
        EiaError: a character EIA has no code for (`#`, `=`, `[` …), with its offset.
    """
    out = bytearray()
    for offset, byte in enumerate(text):
        char = chr(byte).upper()
        if char == "\r":
            continue  # CR LF is one end of block
        code = ISO_TO_EIA.get(char)
        if code is None:
            raise EiaError(f"EIA has no code for {chr(byte)!r} (byte {offset})")
        out.append(code)
    return bytes(out)


def decode(punch: bytes) -> bytes:
    """An EIA punch as ISO text (line ends LF), blank tape and rubbed-out codes skipped.

    Raises:
        EiaError: a code with even parity or no meaning in EIA, with its offset.
    """
    out = bytearray()
    for offset, code in enumerate(punch):
        if code in _SKIPPED:
            continue
        char = EIA_TO_ISO.get(code)
        if char is None:
            kind = "parity error" if bin(code).count("1") % 2 == 0 else "not an EIA code"
            raise EiaError(f"{kind}: 0x{code:02X} (byte {offset})")
        out += char.encode("ascii")
    return bytes(out)
