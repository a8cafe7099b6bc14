"""The programs sent back to a control: a folder's listing, a status report, an error.

Each is a program the control can read in and show: its configured name first, framed as
the control frames programs, every line a comment in the control's comment characters.
Text is made safe for a comment first: printable ASCII only (accents dropped, others
`?`), no character that could end the comment or the program (`(`, `)`, `%`, and the
control's comment characters), capitals if set, cut or wrapped to the line length.
"""

from __future__ import annotations

import difflib
import unicodedata
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import StrEnum

from jobs.fleet.request_settings import RequestSettings

_UNSAFE = "()%"  # would end a comment, or end the program on a tape
_DIALECT_UNSAFE = {"fanuc": "", "heidenhain_iso": ";*", "siemens_iso": ";"}
_REPLACEMENT = "?"
_HEIDENHAIN_END_BLOCK = "N99999999"


@dataclass(frozen=True)
class ListedFile:
    """A file in a listing.

    Attributes:
        name: its name in the folder.
        size: in bytes, None when the source does not say.
        modified: when it last changed (naive: in UTC), None when the source does not say.
    """

    name: str
    size: int | None
    modified: datetime | None


class ReportKind(StrEnum):
    """Which report template a line uses (`ReportFormat`'s fields)."""

    NOT_FOUND = "not_found"  # {path}
    DELETED = "deleted"  # {path}
    RENAMED = "renamed"  # {path}, {new_name}
    REFUSED = "refused"  # {reason}
    FAILED = "failed"  # {path}, {reason}
    SAME = "same"  # {path}
    DIFFERS = "differs"  # {path}, {count}


def report_line(kind: ReportKind, settings: RequestSettings, *, path: str = "",
                new_name: str = "", reason: str = "", count: int = 0) -> str:
    """One line of a report from its template: `NOT FOUND: VIPROS/0010`."""
    template: str = getattr(settings.error_program, kind.value)
    return template.format(path=path, new_name=new_name, reason=reason, count=str(count))


def listing_program(folder: str, entries: list[ListedFile], settings: RequestSettings) -> bytes:
    """The listing of `folder` ("" for the top) as a program, files in the order given."""
    listing = settings.listing
    frame = {"folder": folder or "/", "count": str(len(entries))}
    lines = [(template.format(**frame), False) for template in listing.header]
    shown = entries[:listing.max_files]
    for entry in shown:
        line = listing.line.format(
            name=entry.name, size="" if entry.size is None else str(entry.size),
            date=_in_utc(entry.modified).strftime(listing.date_format) if entry.modified
            else "")
        lines.append((line.rstrip(), True))  # one line a file: cut, never wrapped
    if len(entries) > len(shown):
        lines.append((f"AND {len(entries) - len(shown)} MORE", False))
    if not entries:
        lines.append((listing.empty, False))
    lines += [(template.format(**frame), False) for template in listing.footer]
    return _program(listing.program_name, lines, settings)


def report_program(lines: list[str], settings: RequestSettings) -> bytes:
    """Report lines (`DELETED: VIPROS/0010`) as the report program, long lines wrapped,
    at most `error_program.max_lines` of them."""
    limit = settings.error_program.max_lines
    kept = lines[:limit]
    if len(lines) > limit:
        kept[-1] = f"AND {len(lines) - limit + 1} MORE LINES"
    return _program(settings.error_program.program_name, [(line, False) for line in kept],
                    settings)


def error_program(message: str, settings: RequestSettings) -> bytes:
    """An error (`NOT FOUND: VIPROS/0010`) as the report program."""
    return report_program(error_lines(message), settings)


def error_lines(message: str) -> list[str]:
    """An error's lines as a report holds them (one, empty, for no words)."""
    return message.splitlines() or [""]


def compare_lines(path: str, server: bytes, received: bytes,
                  settings: RequestSettings) -> list[str]:
    """A compare's report: `SAME AS VIPROS/0010`, or `DIFFERS FROM ...` and the differing
    blocks, the server's as `DNC: ...` and the machine's as `CNC: ...`. Blank lines,
    `%` lines and spaces at the ends of blocks are not differences."""
    ours, theirs = _blocks(server), _blocks(received)
    matcher = difflib.SequenceMatcher(a=ours, b=theirs, autojunk=False)
    changes = [op for op in matcher.get_opcodes() if op[0] != "equal"]
    if not changes:
        return [report_line(ReportKind.SAME, settings, path=path)]
    count = sum(max(i2 - i1, j2 - j1) for _, i1, i2, j1, j2 in changes)
    lines = [report_line(ReportKind.DIFFERS, settings, path=path, count=count)]
    for _, i1, i2, j1, j2 in changes:
        lines += [f"DNC: {block}" for block in ours[i1:i2]]
        lines += [f"CNC: {block}" for block in theirs[j1:j2]]
    return lines


def _blocks(text: bytes) -> list[str]:
    decoded = text.decode("utf-8", "replace")
    return [line.strip() for line in decoded.splitlines() if line.strip().strip("%")]


def clean(text: str, settings: RequestSettings) -> str:
    """`text` made safe inside one of the control's comments (see the module docstring)."""
    listing = settings.listing
    unsafe = set(_UNSAFE + _DIALECT_UNSAFE[settings.dialect] + listing.comment_open.strip()
                 + listing.comment_close.strip())
    folded = unicodedata.normalize("NFKD", text)
    folded = "".join(char for char in folded if not unicodedata.combining(char))
    if listing.uppercase:
        folded = folded.upper()
    return "".join(
        " " if char in "\t\r\n" else _REPLACEMENT if char in unsafe or not " " <= char <= "~"
        else char
        for char in folded)


def _in_utc(moment: datetime) -> datetime:
    """The moment in UTC, as the listing's dates are written (a naive one is UTC already)."""
    return moment.astimezone(UTC) if moment.tzinfo is not None else moment.replace(tzinfo=UTC)


def _program(name: str, lines: list[tuple[str, bool]], settings: RequestSettings) -> bytes:
    """A program named `name` whose blocks are comments: (text, cut rather than wrap)."""
    listing = settings.listing
    opening, closing = listing.comment_open, listing.comment_close
    number = listing.block_start
    blocks: list[str] = []
    for text, cut in lines:
        rest = clean(text, settings).rstrip()
        while True:  # one block per piece: the width depends on the block number's
            prefix = f"N{number} " if listing.block_numbers else ""
            width = max(listing.max_line_chars - len(prefix) - len(opening) - len(closing), 8)
            piece, rest = _first_piece(rest, width)
            blocks.append(f"{prefix}{opening}{piece}{closing}")
            number += listing.block_step
            if cut or not rest:
                break
    if listing.end_block:
        end = clean(listing.end_block, settings)
        if settings.dialect == "heidenhain_iso":
            end += " *"
        blocks.append(_numbered(end, number, settings))
    head, tail = _frame(clean(name, settings).replace(_REPLACEMENT, "_"), settings)
    return ("\n".join([*head, *blocks, *tail]) + "\n").encode("ascii")


def _first_piece(text: str, width: int) -> tuple[str, str]:
    """What of `text` fits in `width`, broken at a space where one is, and the rest."""
    if len(text) <= width:
        return text, ""
    space = text.rfind(" ", 1, width + 1)
    at = space if space > 0 else width
    return text[:at].rstrip(), text[at:].lstrip()


def _numbered(block: str, number: int, settings: RequestSettings) -> str:
    return f"N{number} {block}" if settings.listing.block_numbers else block


def _frame(name: str, settings: RequestSettings) -> tuple[list[str], list[str]]:
    """The lines before and after the blocks: the program's start, name and end."""
    if settings.dialect == "heidenhain_iso":
        stem = name.rpartition(".")[0] or name  # 9998.I is the program %9998
        line = f"%{stem} G71 *"
        return [line], [f"{_HEIDENHAIN_END_BLOCK} {line}"]
    if settings.dialect == "siemens_iso":
        stem, dot, kind = name.rpartition(".")
        stem, kind = (stem, kind.upper()) if dot else (name, "MPF")
        stem = "".join(char if char.isalnum() or char == "_" else "_" for char in stem)
        return [f"%_N_{stem}_{kind}", f";$PATH=/_N_{kind}_DIR"], []
    return ["%", name], ["%"]
