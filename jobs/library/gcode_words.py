"""One line of G-code split into its words and comments, for the analysis.

Comments in parentheses and after `;` are taken apart from the code, `%` tape marks and
`N` sequence numbers dropped, a leading `:` read as `O` (the ISO program number), and
Siemens' `X=10` read as `X10`. A line with macro statements (`#`, `[`, `IF`, `GOTO`,
`WHILE`) or Heidenhain plain text is marked so that the analysis can skip it; Siemens
`%_N_NAME_MPF` and Heidenhain `BEGIN PGM NAME MM` give a program name.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

_WORD = re.compile(r"([A-Z])=?([-+]?(?:\d+\.?\d*|\.\d+))")
_PAREN_COMMENT = re.compile(r"\(([^)]*)\)?")  # an unclosed comment runs to the line's end
_MACRO = re.compile(r"[#\[\]]|GOTO|WHILE|\bIF\b|THEN|\bEND\d|\bDO\d")
_SIEMENS_NAME = re.compile(r"^%_N_(\w+?)_(?:MPF|SPF)\b")
_HEIDENHAIN_NAME = re.compile(r"^\s*\d*\s*BEGIN\s+PGM\s+(\S+)(?:\s+(MM|INCH))?")
_HEIDENHAIN = re.compile(r"\b(?:BEGIN\s+PGM|END\s+PGM|TOOL\s+CALL|TOOL\s+DEF|CYCL\s+DEF|"
                         r"FMAX|LBL)\b")


@dataclass(slots=True)
class Words:
    """The words of one line.

    Attributes:
        g: The G codes in order, as numbers (`G01` is 1.0, `G54.1` is 54.1).
        m: The M codes in order, as numbers.
        values: Every other address and its number; a letter given twice keeps the last.
        decimal: The addresses whose number was written with a decimal point (`P1.5`), for
            the rules that read `P1500` and `P1.5` differently.
        comments: The comments of the line, in order, without their delimiters.
        program_number: The `O` number as written (`"0010"`), kept apart for its zeros.
        program_name: A Siemens or Heidenhain program name this line declares.
        skipped: Why the line's code was not read (macro statements, plain text), or "".
    """

    g: list[float] = field(default_factory=list)
    m: list[float] = field(default_factory=list)
    values: dict[str, float] = field(default_factory=dict)
    decimal: set[str] = field(default_factory=set)
    comments: list[str] = field(default_factory=list)
    program_number: str | None = None
    program_name: str | None = None
    skipped: str = ""


def read_words(line: str) -> Words:
    """Split one line into its words and comments.

    Args:
        line: The line, with or without its end of line.

    Returns:
        The words; empty (with `skipped` set) for a line the analysis cannot read.
    """
    words = Words()
    code = line.strip()
    if not code:
        return words
    if code[0] == "%":
        siemens = _SIEMENS_NAME.match(code.upper())
        if siemens:
            words.program_name = siemens.group(1)
        return words
    if "(" in code:
        words.comments.extend(text.strip() for text in _PAREN_COMMENT.findall(code))
        code = _PAREN_COMMENT.sub(" ", code)
    code, semicolon, comment = code.partition(";")
    if semicolon:
        words.comments.append(comment.strip())
    upper = code.upper().strip()
    if not upper:
        return words
    if "PGM" in upper or "FMAX" in upper or "CALL" in upper or "DEF" in upper:
        heidenhain = _HEIDENHAIN_NAME.match(upper)
        if heidenhain:
            words.program_name = heidenhain.group(1)
        if heidenhain or _HEIDENHAIN.search(upper):
            words.skipped = "Heidenhain plain text"
            return words
    if _MACRO.search(upper):
        words.skipped = "macro statements"
        return words
    if upper[0] == ":":
        upper = "O" + upper[1:]
    for letter, number in _WORD.findall(upper):
        value = float(number)
        if letter == "G":
            words.g.append(value)
        elif letter == "M":
            words.m.append(value)
        elif letter == "O":
            words.program_number = number.lstrip("+")
        elif letter != "N":
            words.values[letter] = value
            if "." in number:
                words.decimal.add(letter)
    return words
