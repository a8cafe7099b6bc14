"""Find the commands in a program received from a control: its name, the control header's
commands, and, in the request program only, the commands in its body.

The received text is split in two: the control header is what comes before the program
(before its first `%` or its name line, whichever is first), the body is the rest. Header
commands are cut out between the configured markers; body commands are comments
(`(PRG=0010)`, `;PRG=0010` on controls whose comments start with `;`) or slash words
(`/REQ 111`). Configured regular expressions replace both. Text that is not a program
(binary, NULs, control characters) is refused with a reason, never with an exception.
"""

from __future__ import annotations

import bisect
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

from jobs.fleet.request_settings import Action, RequestSettings, compile_pattern, decode_marker
from worker.transports.serial_tape import NOISE, program_name

__all__ = ["Command", "NotARequest", "Recognised", "Where", "decode_marker", "recognise",
           "same_program"]

Where = Literal["header", "body", "pattern"]

MAX_COMMANDS = 200  # a request with more is refused: no control asks for 200 things at once
_NAME_PEEK_BYTES = 4096  # of a text too large to be a request: where its name is looked for
_ALLOWED_CONTROLS = set("\t\n\r\x0b\x0c")
# XON, XOFF and rubouts; DC2 and DC4 are the punch-on and punch-off codes a control sends
_FLOW_CONTROL = bytes([0x11, 0x13, 0x7F, 0x12, 0x14])
_LINE_END = re.compile(r"\r\n|\r|\n")
_TRAILING_NON_LETTERS = re.compile(r"[^A-Za-z]+$")
_LINE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n|$)")
_PAREN_COMMENT = re.compile(r"\(([^()\r\n]*)\)")
_O_NUMBER = re.compile(r"O0*(\d{1,8})", re.IGNORECASE)
_HEIDENHAIN_NAME = re.compile(r"%\s*(\S+)\s+G7[01]\b|BEGIN\s+PGM\s+(\S+)", re.IGNORECASE)
_SIEMENS_NAME = re.compile(r"%_N_([A-Za-z0-9_]+?)_(MPF|SPF)\b", re.IGNORECASE)
_SEMICOLON_DIALECTS = ("heidenhain_iso", "siemens_iso")
_BARE = (Action.LIST, Action.SKIP)  # commands a comment may give without a body


class NotARequest(ValueError):
    """The received text cannot be read as a program, or is too large to be a request."""

    def __init__(self, reason: str, *, program_name: str | None = None,
                 is_request: bool = False) -> None:
        super().__init__(reason)
        self.program_name = program_name  # when the text says it, though it is refused
        self.is_request = is_request  # it asks for something: its operator waits to read why


@dataclass(frozen=True)
class Command:
    """One command found in the received text.

    Attributes:
        name: as written (`PRG`).
        body: its value (`0010`), "" when it has none.
        action: what the settings map the name to; None for a name they do not know.
        where: found in the control header, the program body, or by a configured pattern.
        line: the line it is on, from 1.
    """

    name: str
    body: str
    action: Action | None
    where: Where
    line: int


@dataclass(frozen=True)
class Recognised:
    """What a received text is.

    Attributes:
        program_name: the name the program gives itself (`O8888`, `1234`, `PART1.MPF`),
            None when it gives none.
        is_request: it asks dncq for something (see `recognise`).
        commands: every command found, in the order of the text.
        refused: why the text is not read at all (binary, too large a request); then
            `commands` is empty, and `is_request` says whether it was a request all the
            same (the request program), refused with an answer saying why.
        notes: what a user may want to know (a large program not searched for requests).
    """

    program_name: str | None
    is_request: bool
    commands: list[Command] = field(default_factory=list)
    refused: str | None = None
    notes: list[str] = field(default_factory=list)


def recognise(text: bytes, settings: RequestSettings) -> Recognised:
    """The name, the commands and whether `text` is a request.

    A text is a request when it has a header command with an action to run (not skip,
    not received-name, not unknown), or, with body commands on, when it is the request
    program: named `settings.request_program` by its first line or by a received-name
    header command.
    """
    try:
        return _recognise(text, settings)
    except NotARequest as exc:
        return Recognised(program_name=exc.program_name, is_request=exc.is_request,
                          refused=str(exc))


def _recognise(raw: bytes, settings: RequestSettings) -> Recognised:
    if len(raw) > settings.max_request_bytes:
        return _too_large(raw, settings)
    text = _Text(_decoded(raw, settings))
    name, name_at = _program_name(text.text, settings)
    # The header ends where the program starts: its first `%` or its name line.
    ends = [at for at in (text.text.find("%"), name_at) if at is not None and at >= 0]
    header_end = min(ends, default=len(text.text))
    commands = [] if settings.where == "body" else list(_commands_in(
        text, 0, header_end, settings, "header"))
    given = [c.body for c in commands if c.action is Action.RECEIVED_NAME and c.body]
    header_request = any(c.action not in (None, Action.SKIP, Action.RECEIVED_NAME)
                         for c in commands)
    is_request_program = same_program(given[-1] if given else name, settings.request_program)
    body_request = settings.where != "header" and is_request_program
    if body_request:
        commands += _commands_in(text, header_end, len(text.text), settings, "body")
    if len(commands) > MAX_COMMANDS:
        raise NotARequest(f"the request has {len(commands)} commands; at most {MAX_COMMANDS} "
                          f"are read", program_name=name,
                          is_request=header_request or body_request)
    return Recognised(program_name=name, is_request=header_request or body_request,
                      commands=commands)


def _too_large(raw: bytes, settings: RequestSettings) -> Recognised:
    peek = raw[:_NAME_PEEK_BYTES].strip(NOISE).decode("latin-1")
    name, _ = _program_name(peek, settings)
    size = f"{len(raw):,} bytes, more than the {settings.max_request_bytes:,} a request may have"
    if same_program(name, settings.request_program):
        raise NotARequest(f"the request program {name} is {size}", program_name=name,
                          is_request=True)
    return Recognised(program_name=name, is_request=False,
                      notes=[f"not searched for requests: {size}"])


def _decoded(raw: bytes, settings: RequestSettings) -> str:
    """The text without tape noise; refused if it is not text a control sends."""
    body = raw.strip(NOISE + b" \t\r\n\x1a")  # leader, trailer, a DOS end-of-file mark
    body = body.translate(None, _FLOW_CONTROL)
    if not body:
        raise NotARequest("the text is empty (only blank tape or spaces)")
    if (at := body.find(b"\x00")) >= 0:
        raise NotARequest(f"a NUL byte at offset {at} inside the text: binary data, "
                          f"not a program")
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        text = body.decode("latin-1")  # an older control's comments: one byte a character
    allowed = _ALLOWED_CONTROLS | set(settings.header.start_text + settings.header.end_text)
    for at, char in enumerate(text):
        if (char < " " or "\x7f" <= char <= "\x9f") and char not in allowed:
            raise NotARequest(f"control character 0x{ord(char):02X} at offset {at}: "
                              f"binary data, not a program")
    return text


class _Text:
    """The decoded text and where its lines start, for line numbers by offset."""

    def __init__(self, text: str) -> None:
        self.text = text
        self._starts = [0, *(m.end() for m in _LINE_END.finditer(text))]

    def line_of(self, at: int) -> int:
        """The line, from 1, that offset `at` is on."""
        return bisect.bisect_right(self._starts, at)


def _lines(text: str, start: int = 0, end: int | None = None) -> Iterator[tuple[int, str]]:
    """(offset, line without its end) of each line of `text[start:end]`."""
    end = len(text) if end is None else end
    for match in _LINE.finditer(text, start, end):
        if match.start() == match.end():
            break
        yield match.start(), match.group().rstrip("\r\n")


def _program_name(text: str, settings: RequestSettings) -> tuple[str | None, int | None]:
    """The program's name and the offset of the line that gives it."""
    marker = settings.header.start_text if settings.where != "body" else None
    for at, line in _lines(text):
        bare = line.strip(" \t")
        if not bare.strip("%") or bare.startswith(("(", ";")) or (marker and _in_header(
                bare, marker)):
            continue
        if settings.dialect == "heidenhain_iso" and (m := _HEIDENHAIN_NAME.match(bare)):
            return m.group(1) or m.group(2), at
        if settings.dialect == "siemens_iso" and (m := _SIEMENS_NAME.match(bare)):
            return f"{m.group(1)}.{m.group(2).upper()}", at
        return program_name(bare.encode("latin-1", "replace")), at
    return None, None


def _in_header(line: str, marker: str) -> bool:
    # A marker that starts with a control character (ESC) is never part of a program: a
    # line that has it is header. A printable one (`(`) only when it starts the line.
    return line.startswith(marker) or (not marker[0].isprintable() and marker in line)


def same_program(name: str | None, wanted: str) -> bool:
    """Whether `name` is the program `wanted`: O-numbers by number (`O8888` is `O08888`),
    other names without regard to case, a `wanted` without extension matching any."""
    if name is None:
        return False
    numbers = [_O_NUMBER.fullmatch(n) for n in (name, wanted)]
    if numbers[0] and numbers[1]:
        return int(numbers[0].group(1)) == int(numbers[1].group(1))
    if "." not in wanted:
        name = name.rpartition(".")[0] or name
    return name.casefold() == wanted.casefold()


def _commands_in(text: _Text, start: int, end: int, settings: RequestSettings,
                 where: Literal["header", "body"]) -> Iterator[Command]:
    if settings.patterns:
        yield from _pattern_commands(text, start, end, settings)
    elif where == "header":
        yield from _header_commands(text, start, end, settings)
    else:
        for at, line in _lines(text.text, start, end):
            yield from _body_commands(line, text.line_of(at), settings)


def _command(name: str, body: str, where: Where, line: int,
             settings: RequestSettings) -> Command:
    return Command(name=name, body=body, action=settings.action_of(name), where=where,
                   line=line)


def _pattern_commands(text: _Text, start: int, end: int,
                      settings: RequestSettings) -> Iterator[Command]:
    found: list[tuple[int, Command]] = []
    for pattern in settings.patterns:
        compiled = compile_pattern(pattern)
        named = {"command", "body"} <= set(compiled.groupindex)
        for match in compiled.finditer(text.text, start, end):
            name, body = match.group("command", "body") if named else match.group(1, 2)
            if name and name.strip():
                found.append((match.start(), _command(
                    name.strip(), (body or "").strip(), "pattern", text.line_of(match.start()),
                    settings)))
    yield from (command for _, command in sorted(found, key=lambda pair: pair[0]))


def _header_commands(text_of: _Text, start: int, end: int,
                     settings: RequestSettings) -> Iterator[Command]:
    text, header = text_of.text, settings.header
    opening, closing, separator = header.start_text, header.end_text, header.separator_text
    at = start
    while (found := text.find(opening, at, end)) >= 0:
        begin = found + len(opening)
        line_end = min(i for i in (text.find("\n", begin, end), text.find("\r", begin, end),
                                   end) if i >= 0)
        close = text.find(closing, begin, end) if closing else -1
        stop = close if close >= 0 else line_end
        at = stop + (len(closing) if close >= 0 else 0)
        segment = text[begin:stop].strip()
        if header.name_chars:
            name, body = segment[:header.name_chars], segment[header.name_chars:]
        else:
            name, _, body = segment.partition(separator)
        if header.letters_only:  # `H0` of `H0010` is the name `H`, the body `0010`
            kept = _TRAILING_NON_LETTERS.sub("", name)
            name, body = kept, name[len(kept):] + body
        if separator and body.startswith(separator):
            body = body[len(separator):]
        if name.strip():
            yield _command(name.strip(), body.strip(), "header", text_of.line_of(found),
                           settings)


def _body_commands(line: str, number: int, settings: RequestSettings) -> Iterator[Command]:
    """The commands on one line of the body, left to right."""
    found: list[tuple[int, str, str]] = []
    rest = line
    if settings.body_syntax != "slash":
        for match in _PAREN_COMMENT.finditer(line):
            found.extend((match.start(), *pair) for pair in _comment_command(
                match.group(1), settings))
        rest = _PAREN_COMMENT.sub(lambda m: " " * len(m.group()), line)
        if settings.dialect in _SEMICOLON_DIALECTS and (semi := rest.find(";")) >= 0:
            inner = rest[semi + 1:].rstrip(" \t*")
            found.extend((semi, *pair) for pair in _comment_command(inner, settings))
            rest = rest[:semi]
    if settings.body_syntax != "comment":
        for match in _slash_pattern(settings).finditer(rest):
            found.append((match.start(), match.group(1), match.group(2) or ""))
    for _, name, body in sorted(found, key=lambda item: item[0]):
        yield _command(name, body, "body", number, settings)


def _comment_command(inner: str, settings: RequestSettings) -> list[tuple[str, str]]:
    """`PRG=0010` as (name, body); a bare configured name of a command that takes no body
    (`LST`) as (name, ""). Any other bare name is a comment: a title such as `(REQ)` on the
    request's name line asks for nothing."""
    name, separator, body = inner.partition(settings.body_separator)
    name = name.strip()
    if separator and re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name):
        return [(name, body.strip())]
    if not separator and settings.action_of(name) in _BARE:
        return [(name, "")]
    return []


def _slash_pattern(settings: RequestSettings) -> re.Pattern[str]:
    # A word after a slash command is its body, unless it is itself a known slash command:
    # `/DIR VIPROS/OLD` and `/REQ 111 /REQ 222` both read as meant.
    known = "|".join(re.escape(name) for name in settings.commands) or "(?!)"
    return re.compile(rf"(?<!\S)/\s*([A-Za-z][A-Za-z0-9_]*)"
                      rf"(?:[ \t]+(?!/(?:{known})(?:\s|$))(\S+))?", re.IGNORECASE)
