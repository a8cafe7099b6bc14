"""What a received program says of itself: its program number (or name) and first comment.

Pure: bytes in, text out, no I/O. Read as Latin-1, so that any byte is a character and a
program in any code page is described rather than refused. Headers understood:

- Fanuc, Haas, Mitsubishi and other ISO controls: `O0010`, `O0010 (BRACKET)`, the ISO tape
  form `:0010`, with or without the `%` lines of the tape (the number as `O` and at least
  four digits, as the serial link names a punch);
- Heidenhain: `0 BEGIN PGM BRACKET MM` (`BRACKET.H`) and the ISO `%BRACKET G71 *`
  (`BRACKET.I`);
- Siemens: the tape header `%_N_BRACKET_MPF` (`BRACKET.MPF`, also `_SPF`) and the older
  `%MPF123` (`MPF123`).

The first comment is the first non-empty `( ... )` comment, or text after `;` (Heidenhain,
Siemens), anywhere in the program.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass

MAX_COMMENT_CHARS = 255  # inbox_items.comment
MAX_NUMBER_CHARS = 64  # inbox_items.program_number
_NOISE = "\x00\x11\x13\x7f"  # blank tape, XON/XOFF, rubbed-out characters
_LINE_ENDS = re.compile(r"\r\n|\r|\n")
_ISO_NUMBER = re.compile(r"[O:]\s*([0-9]{1,8})(?![0-9])", re.IGNORECASE)
_HEIDENHAIN = re.compile(r"(?:[0-9]+\s+)?BEGIN\s+PGM\s+([^\s;]+)", re.IGNORECASE)
_HEIDENHAIN_ISO = re.compile(r"%([A-Za-z0-9_-]{1,60})\s+G7[01]\b", re.IGNORECASE)
_SIEMENS_TAPE = re.compile(r"%_N_([A-Za-z0-9_]{1,60})_(MPF|SPF)\b", re.IGNORECASE)
_SIEMENS_OLD = re.compile(r"%((?:MPF|SPF|L)[0-9]{1,8})\b", re.IGNORECASE)
_PAREN_COMMENT = re.compile(r"\(([^()]*)\)?")


@dataclass(frozen=True)
class Described:
    """What a program says of itself; None where it says nothing."""

    program_number: str | None  # O0010; a Heidenhain or Siemens program: its file name
    comment: str | None  # its first comment, trimmed


def describe(data: bytes) -> Described:
    """The program number (or name) and first comment of a program's bytes."""
    text = data.decode("latin-1").translate({ord(c): None for c in _NOISE})
    lines = [line.strip() for line in _LINE_ENDS.split(text)]
    return Described(program_number=_number(lines), comment=_first_comment(lines))


def _number(lines: list[str]) -> str | None:
    """The header of the first line that is more than `%` or a comment."""
    for line in lines:
        if line.startswith("%"):
            named = _percent_header(line)
            if named is not None:
                return named
            line = line[1:].strip()  # `%` alone, or `%O0010` run together
        bare = _PAREN_COMMENT.sub("", line).strip()
        if not bare or bare.startswith(";"):
            continue
        iso = _ISO_NUMBER.match(bare)
        if iso:
            return f"O{int(iso.group(1)):04d}"
        heidenhain = _HEIDENHAIN.match(bare)
        if heidenhain:
            return f"{heidenhain.group(1)}.H"[:MAX_NUMBER_CHARS]
        return None  # the program begins without a header
    return None


def _percent_header(line: str) -> str | None:
    """A Siemens or Heidenhain ISO header on a `%` line, as the control names the file."""
    siemens = _SIEMENS_TAPE.match(line)
    if siemens:
        return f"{siemens.group(1)}.{siemens.group(2).upper()}"
    old = _SIEMENS_OLD.match(line)
    if old:
        return old.group(1).upper()
    heidenhain = _HEIDENHAIN_ISO.match(line)
    if heidenhain:
        return f"{heidenhain.group(1)}.I"
    return None


def _first_comment(lines: list[str]) -> str | None:
    for comment in _comments(lines):
        if comment:
            return comment[:MAX_COMMENT_CHARS]
    return None


def _comments(lines: list[str]) -> Iterator[str]:
    """Each comment of each line, in order, trimmed (empty ones too)."""
    for line in lines:
        if line.startswith("%"):
            continue  # a tape header; Siemens' `;$PATH=` is not a comment either
        for match in _PAREN_COMMENT.finditer(line):
            yield match.group(1).strip()
        _, semicolon, after = _PAREN_COMMENT.sub("", line).partition(";")
        if semicolon and not after.lstrip().startswith("$"):
            yield after.strip()
