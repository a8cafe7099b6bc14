"""The parts of a machine's request settings that say how text is written: header markers,
file names, the listing and report programs; and the checks their fields share."""

from __future__ import annotations

import re
import string
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

_ESCAPE = re.compile(r"#(#|[0-9A-Fa-f]{2})")
_UNSAFE_IN_NAME = re.compile(r"[\x00-\x1f\x7f/\\:*?\"<>|]")


def decode_marker(text: str) -> str:
    """A marker written with `#XX` escapes as its characters: `#1B#26` is ESC `&`.

    `##` is one `#` (so a marker can contain it); any other `#` must start two hex digits.
    Written characters must be printable ASCII (32-126): others are given as `#XX`.

    Raises:
        ValueError: a `#` that starts no escape, or a character that is not printable ASCII.
    """
    out: list[str] = []
    at = 0
    while at < len(text):
        char = text[at]
        if char == "#":
            match = _ESCAPE.match(text, at)
            if not match:
                raise ValueError(f"{text!r}: '#' at {at} is not '##' or '#' and two hex digits "
                                 f"(such as #1B)")
            escape = match.group(1)
            out.append("#" if escape == "#" else chr(int(escape, 16)))
            at = match.end()
            continue
        if not " " <= char <= "~":
            hint = f"; write it as #{ord(char):02X}" if ord(char) < 256 else ""
            raise ValueError(f"{text!r}: {char!r} is not printable ASCII{hint}")
        out.append(char)
        at += 1
    return "".join(out)


def check_relative_folder(folder: str, *, what: str = "folder") -> str:
    """A `/`-separated folder below a top (`VIPROS/OLD`, "" for the top itself).

    Raises:
        ValueError: an absolute folder, a `..` or `.` step, an empty step or an unsafe name.
    """
    if not folder:
        return ""
    if folder.startswith(("/", "\\")) or re.match(r"[A-Za-z]:", folder):
        raise ValueError(f"{what} {folder!r} is absolute")
    for step in folder.split("/"):
        if step in ("", ".", ".."):
            raise ValueError(f"{what} {folder!r} has a {step or 'empty'!r} step")
        check_file_name(step, what=what)
    return folder


def check_file_name(name: str, *, what: str = "file name") -> str:
    """A plain, safe, single file name: no `/`, `\\`, `..`, control or reserved characters.

    Raises:
        ValueError: what is wrong with it.
    """
    if not name or name in (".", ".."):
        raise ValueError(f"{what} {name!r} is not a name")
    if len(name) > 255:
        raise ValueError(f"{what} is longer than 255 characters")
    if match := _UNSAFE_IN_NAME.search(name):
        raise ValueError(f"{what} {name!r} may not contain {match.group()!r}")
    if name != name.strip() or name.startswith(".dncq-"):
        raise ValueError(f"{what} {name!r} starts or ends with spaces, or is dncq's own")
    return name


def check_template(template: str, fields: set[str]) -> str:
    """A `str.format` template using only `fields` (no attribute or index access).

    Raises:
        ValueError: a field that is not one of `fields`, or a template that does not parse.
    """
    try:
        parsed = list(string.Formatter().parse(template))
    except ValueError as exc:
        raise ValueError(f"template {template!r} does not parse: {exc}") from None
    for _text, field, _spec, _conversion in parsed:
        if field is not None and field not in fields:
            raise ValueError(f"template {template!r}: {{{field}}} is not one of "
                             f"{', '.join('{' + f + '}' for f in sorted(fields))}")
    try:  # every field is given as text: a spec such as `>8` works, `d` does not
        template.format(**{f: "X" for f in fields})
    except (ValueError, TypeError) as exc:
        raise ValueError(f"template {template!r}: {exc} (fields are text)") from None
    return template


class Model(BaseModel):
    """Base of the request settings models: unknown fields refused, field docstrings kept."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


class HeaderFormat(Model):
    """How commands are cut out of the control header sent before the program."""

    start: str = "("
    """What starts a command, with `#XX` escapes (`#1B#26` is ESC `&`); what comes before
    it is not a command."""
    end: str = ")"
    """What ends a command, with `#XX` escapes; "" ends it at the end of its line."""
    name_chars: int = Field(default=0, ge=0, le=64)
    """The first N characters are the command name; 0: the name runs to the separator."""
    letters_only: bool = False
    """The name is letters only: trailing non-letters of the first N characters go to the
    front of the body (`H0010` with N=2 is `H` and `0010`)."""
    separator: str = "="
    """Between the name and the body (`H=0010`); stripped from the front of the body."""

    @field_validator("start", "end", "separator")
    @classmethod
    def _escapes_decode(cls, value: str) -> str:
        decode_marker(value)
        return value

    @model_validator(mode="after")
    def _a_name_can_be_found(self) -> HeaderFormat:
        if not self.start:
            raise ValueError("header.start is required: what starts a command")
        if self.name_chars == 0 and not self.separator:
            raise ValueError("give header.name_chars or a header.separator: without either "
                             "a command has no end to its name")
        return self

    @property
    def start_text(self) -> str:
        """`start` with its escapes decoded."""
        return decode_marker(self.start)

    @property
    def end_text(self) -> str:
        """`end` with its escapes decoded."""
        return decode_marker(self.end)

    @property
    def separator_text(self) -> str:
        """`separator` with its escapes decoded."""
        return decode_marker(self.separator)


class NamingRules(Model):
    """How a command's body becomes a file name (see `jobs.requests.naming`)."""

    prefix: str = ""
    """Put before the name (after padding)."""
    suffix: str = ""
    """Put after the name, before the extension."""
    extension: str = ""
    """Without its dot: `NC`, `MPF`; "" for none."""
    extension_mode: Literal["replace", "add", "remove", "keep"] = "keep"
    """replace: the body's extension becomes `extension`; add: `extension` always added;
    remove: the body's extension dropped; keep: the body's kept, `extension` added when it
    has none."""
    pad_to: int = Field(default=0, ge=0, le=64)
    """A number shorter than this is padded on its left (`10` to `0010`); 0: no padding."""
    pad_char: str = Field(default="0", min_length=1, max_length=1)
    """The padding character."""
    ignore_chars: str = ""
    """Characters dropped from the body (spaces, quotes a control adds)."""
    number_letter: str = Field(default="", max_length=1)
    """A letter written before a program number that is not part of the file name: with
    `O`, `O10` names the same file as `10`."""

    @field_validator("prefix", "suffix", "extension", "pad_char", "number_letter")
    @classmethod
    def _allowed_in_a_name(cls, value: str) -> str:
        if match := _UNSAFE_IN_NAME.search(value):
            raise ValueError(f"{value!r}: {match.group()!r} is not allowed in a file name")
        return value

    @field_validator("extension")
    @classmethod
    def _no_dot(cls, value: str) -> str:
        if value.startswith("."):
            raise ValueError("give the extension without its dot: NC, not .NC")
        return value


LISTING_FIELDS = {"name", "size", "date"}
LISTING_FRAME_FIELDS = {"folder", "count"}


class ListingFormat(Model):
    """The program a folder listing is sent as, and how every answer program is written."""

    program_name: str = "O8889"
    """The listing program's name, as the control names programs."""
    header: list[str] = ["{folder}: {count} FILES"]
    """Lines before the files; `{folder}` and `{count}`."""
    line: str = "{name} {size} {date}"
    """One line per file: `{name}`, `{size}` (bytes), `{date}`; format specs allowed
    (`{name:<12}`)."""
    max_files: int = Field(default=200, ge=1, le=10_000)
    """The most files listed (a control's memory is small); more are counted in one line."""
    empty: str = "NO FILES"
    """The line instead of the files when the folder has none."""
    footer: list[str] = ["END OF LIST"]
    """Lines after the files; `{folder}` and `{count}`."""
    date_format: str = "%Y-%m-%d %H:%M UTC"
    """strftime format of `{date}`, a time in UTC (`%Z` writes `UTC`)."""
    block_numbers: bool = False
    """Number the lines (`N10 (…)`)."""
    block_start: int = Field(default=10, ge=0)
    """The first block number."""
    block_step: int = Field(default=10, ge=1)
    """Between block numbers."""
    comment_open: str = "("
    """What starts a comment on this control."""
    comment_close: str = ")"
    """What ends it; "" when a comment runs to the end of its line (`;`)."""
    max_line_chars: int = Field(default=60, ge=20, le=256)
    """The longest line written, block number and comment characters included."""
    uppercase: bool = True
    """Write text in capitals (older controls refuse small letters)."""
    end_block: str = "M30"
    """The block before the program's end ("" for none)."""

    @field_validator("header", "footer")
    @classmethod
    def _frame_fields(cls, value: list[str]) -> list[str]:
        return [check_template(line, LISTING_FRAME_FIELDS) for line in value]

    @field_validator("line")
    @classmethod
    def _line_fields(cls, value: str) -> str:
        return check_template(value, LISTING_FIELDS)

    @field_validator("comment_open")
    @classmethod
    def _an_opening(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("comment_open is required: what starts a comment, ( or ;")
        return value

    @field_validator("program_name")
    @classmethod
    def _program_name(cls, value: str) -> str:
        return check_file_name(value, what="program_name")


REPORT_FIELDS = {"path", "new_name", "reason", "count"}


class ReportFormat(Model):
    """The program an error or the status of a delete, rename or compare is sent as
    (written as `listing` says: comment characters, block numbers, capitals)."""

    program_name: str = "O8890"
    """The report program's name."""
    not_found: str = "NOT FOUND: {path}"
    """A file asked for that no source has."""
    deleted: str = "DELETED: {path}"
    """A delete done."""
    renamed: str = "RENAMED: {path} TO {new_name}"
    """A rename done."""
    refused: str = "REFUSED: {reason}"
    """A request not run, and why."""
    failed: str = "FAILED: {path}: {reason}"
    """An operation that failed."""
    same: str = "SAME AS {path}"
    """A compared program equal to the server's copy."""
    differs: str = "DIFFERS FROM {path}: {count} BLOCKS"
    """A compared program that differs; the differing blocks follow."""
    max_lines: int = Field(default=40, ge=1, le=1000)
    """The longest report, in lines (a compare of two unrelated programs is cut)."""

    @field_validator("not_found", "deleted", "renamed", "refused", "failed", "same",
                     "differs")
    @classmethod
    def _report_fields(cls, value: str) -> str:
        return check_template(value, REPORT_FIELDS)

    @field_validator("program_name")
    @classmethod
    def _program_name(cls, value: str) -> str:
        return check_file_name(value, what="program_name")
