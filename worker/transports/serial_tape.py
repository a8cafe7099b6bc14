"""A program as a tape: the lines of a stream, the framed punch, and the name a punch carries.

Shared by the `serial` transport and the simulated control's RS-232 side, so both read a
tape the same way.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator

NUL, DC1, DC3, DEL = 0x00, 0x11, 0x13, 0x7F
XON, XOFF = bytes([DC1]), bytes([DC3])
_LINE_ENDS = re.compile(rb"\r\n|\r|\n")
_O_NUMBER = re.compile(rb"\s*[O:]\s*([0-9]{1,8})")
_PLAIN_NAME = re.compile(rb"\s*([A-Za-z0-9][A-Za-z0-9_.-]{0,63})")
# A first word that is a block of G-code, no name: a number (`12 G0`), or one address and
# its value (`N10`, `G0`, `X10.5`).
_NOT_A_NAME = re.compile(rb"[0-9.+-]+|[A-Za-z][+-]?[0-9.]+")
_BEGIN_PGM = re.compile(rb"\s*[0-9]*\s*BEGIN\s+PGM\s+(\S+)", re.IGNORECASE)
_HEIDENHAIN_NAME = re.compile(rb"[A-Za-z0-9_-]{1,60}")
NOISE = bytes([NUL, DC1, DC3, DEL])
"""Blank tape, flow control and rubbed-out characters: never part of a program."""


def lines_of(chunks: Iterable[bytes]) -> Iterator[bytes]:
    """The lines of a byte stream without their ends (CR, LF or CR LF), read lazily.

    A final line without an end is a line; an empty stream has none.
    """
    rest = b""
    for chunk in chunks:
        rest += chunk
        if rest.endswith(b"\r"):
            head, rest = rest[:-1], b"\r"  # its LF may be in the next chunk
        else:
            head, rest = rest, b""
        *done, partial = _LINE_ENDS.split(head)
        yield from done
        rest = partial + rest
    if rest:
        yield rest.rstrip(b"\r")


def program_body(lines: Iterable[bytes], *, start: bytes, end: bytes) -> Iterator[bytes]:
    """The lines without the program's own framing: a first line that is only `start`
    and a last line that is only `end` (the punch adds its own)."""
    return (line for line in own_framing_marked(lines, start=start, end=end)
            if line is not None)


def own_framing_marked(lines: Iterable[bytes], *, start: bytes, end: bytes
                       ) -> Iterator[bytes | None]:
    """One item for each line: the line, or None for the program's own framing (a first
    line that is only `start`, a last line that is only `end`, and the blank lines before
    the one and after the other), which a link that frames the program itself must not
    send again: a second start character on the tape ends it before its first block. One
    out for each in, so that a drip-feed's lines keep their numbers."""
    begun = False  # a line that says something came
    held: list[bytes] = []  # a line that is only `end` and blank ones: the tail, or not
    for line in lines:
        said = line.strip()
        if not begun:
            begun = bool(said)
            if not said or said == start:
                yield None
                continue
        if said == end or (held and not said):
            held.append(line)
            continue
        yield from held
        held.clear()
        yield line
    if any(h.strip() == end for h in held):
        yield from (None for _ in held)
    else:
        yield from held


def program_name(text: bytes) -> str | None:
    """The name a program gives itself on its first line that says anything: its O-number
    as a Fanuc names it (`O1234`, also from the ISO `:1234`), a Heidenhain's `BEGIN PGM
    NAME` as `NAME.H`, else a plain first word that is not a block (`N10`, `G0`, `12`):
    None when there is none, and whoever names it falls back to a name of its own, where a
    block's first word made unrelated programs share a name."""
    for line in _LINE_ENDS.split(text):
        stripped = line.strip(b" \t%" + NOISE)
        if not stripped or stripped.startswith(b"("):
            continue
        number = _O_NUMBER.match(stripped)
        if number:
            return f"O{int(number.group(1)):04d}"
        if begin := _BEGIN_PGM.match(stripped):
            name = begin.group(1)
            return f"{name.decode('ascii')}.H" if _HEIDENHAIN_NAME.fullmatch(name) else None
        plain = _PLAIN_NAME.match(stripped)
        if plain is None or _NOT_A_NAME.fullmatch(plain.group(1)):
            return None
        return plain.group(1).decode("ascii")
    return None
