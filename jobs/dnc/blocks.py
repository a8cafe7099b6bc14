"""One line of an ISO (Fanuc-style) program read as a block: its words, or why it is not one.

Comments in parentheses and everything after `;` are dropped, `%` tape marks ignored and a
leading `:` read as `O` (the ISO program number). A line made only of address words (a
letter and a number) is a plain block; anything else is a macro statement, Heidenhain plain
text, or unreadable, and the scan that meets it decides what that means.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from enum import StrEnum

# A plain block: an optional block-delete slash, then address words only.
_PLAIN = re.compile(r"\s*/?(?:\s*[A-Z]\s*[-+]?(?:\d+\.?\d*|\.\d+))*\s*")
_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_COMMENT = re.compile(r"\([^)]*\)?")  # an unclosed comment runs to the end of the line
_HEIDENHAIN = re.compile(r"\b(?:BEGIN\s+PGM|END\s+PGM|TOOL\s+CALL|TOOL\s+DEF|CYCL\s+DEF)\b")
_MACRO = re.compile(r"[#\[\]=]|GOTO|WHILE|IF|THEN|\bDO\d|END\d|POPEN|PCLOS|DPRNT|BPRNT")


class BlockKind(StrEnum):
    """What a line turned out to be."""

    PLAIN = "plain"  # address words only (or nothing: a comment, a `%`, a blank line)
    MACRO = "macro"  # variables, expressions or branching: #1=…, IF[…]GOTO, WHILE…DO1
    HEIDENHAIN = "heidenhain"  # Klartext: BEGIN PGM, TOOL CALL, CYCL DEF…
    UNREADABLE = "unreadable"  # none of the above


@dataclass(frozen=True, slots=True)
class Block:
    """One line as the scan reads it.

    Attributes:
        kind: What the line is.
        text: The code without comments, upper case, for messages.
        g: The G codes in order, numbers without leading zeros (`G01` is `"1"`, `G54.1`
            is `"54.1"`).
        m: The M codes, likewise (`M08` is `"8"`).
        values: Every other address and its number as written (`{"S": "1200"}`); a
            letter given twice keeps its last value.
    """

    kind: BlockKind
    text: str
    g: tuple[str, ...] = ()
    m: tuple[str, ...] = ()
    values: dict[str, str] = field(default_factory=dict)


def read_block(line: str) -> Block:
    """Read one line of a program as a block.

    Args:
        line: The line, with or without its end of line.

    Returns:
        The block; only a `PLAIN` block has words.
    """
    upper = line.upper()
    code = _COMMENT.sub("", upper) if "(" in upper else upper
    code = code.split(";", 1)[0].replace("%", "").strip()
    if code.startswith(":"):
        code = "O" + code[1:]
    if not _PLAIN.fullmatch(code):
        if _HEIDENHAIN.search(upper):
            return Block(BlockKind.HEIDENHAIN, code)
        if _MACRO.search(code):
            return Block(BlockKind.MACRO, code)
        return Block(BlockKind.UNREADABLE, code)
    g: list[str] = []
    m: list[str] = []
    values: dict[str, str] = {}
    for letter, number in _WORD.findall(code):
        if letter == "G":
            g.append(_code_number(number))
        elif letter == "M":
            m.append(_code_number(number))
        else:
            values[letter] = number
    return Block(BlockKind.PLAIN, code, tuple(g), tuple(m), values)


def _code_number(number: str) -> str:
    """A G or M number without its leading zeros: `01` is `1`, `054.1` is `54.1`."""
    whole, dot, fraction = number.lstrip("+").partition(".")
    return (whole.lstrip("0") or "0") + dot + fraction
