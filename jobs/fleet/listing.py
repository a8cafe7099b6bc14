"""What a machine's listing names: which names can be read, walked into or given at all,
and what a walk makes of each, a file it gives (`WalkedFile`) or one it leaves out, and why.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from worker.transports.base import Entry

log = logging.getLogger(__name__)

NOT_TEXT = "its name is not text in the machine's encoding"
NOT_A_FOLDER_NAME = "its name holds '/', '\\' or NUL, so it cannot be walked into"
NOT_A_FILE_NAME = "its name is '.' or '..' or holds '/' or NUL, so it names no file of its folder"


@dataclass(frozen=True)
class LeftOut:
    """A file or folder a walk found but could not give, and why."""

    path: str  # in the model's notation; bytes that are not text escaped (`bad\xffname.nc`)
    is_dir: bool
    reason: str


@dataclass(frozen=True)
class WalkedFile:
    """A file found by a walk: its folder relative to the start, and its entry."""

    parts: tuple[str, ...]
    entry: Entry
    storage: str


def is_folder_name(name: str) -> bool:
    """Whether a folder a machine listed can be walked into: a name, not a path."""
    return name not in ("", ".", "..") and not any(c in name for c in "/\\\0")


def is_file_name(name: str) -> bool:
    """Whether a file a machine listed names a file of its folder: not a path (`x/y`) nor a
    step (`.`, `..`). A `\\` is a letter of the name on a machine that stores it."""
    return name not in ("", ".", "..") and not any(c in name for c in "/\0")


def is_text(name: str) -> bool:
    """Whether a name from the machine is text: bytes that were not UTF-8 (or the machine's
    encoding) arrive as lone surrogates, which no JSON answer can carry."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def as_bytes(name: str) -> str:
    """A name that is not text, as its bytes escaped (`bad\\xffname.nc`)."""
    return repr(name.encode("utf-8", "surrogateescape"))[2:-1]


def nameable(entries: list[Entry]) -> list[Entry]:
    """The entries a listing can name; the others are logged."""
    kept = [e for e in entries if is_text(e.name)]
    if len(kept) < len(entries):
        names = [as_bytes(e.name) for e in entries if not is_text(e.name)]
        log.warning("left %d names that are not text out: %s", len(names), ", ".join(names))
    return kept
