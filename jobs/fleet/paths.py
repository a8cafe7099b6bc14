"""The contract's path and name rules: `dirAtCNC`/`subDir` to a place inside a machine's roots.

A place is a root (in the model's notation, e.g. `//CNC_MEM/`, `TNC:\\nc_prog`)
and folder names below it. Its storage path, what a transport sees, is the root
with drive colons and separators folded into a POSIX path (`TNC:\\nc_prog\\a`
becomes `TNC/nc_prog/a`), so that every root is a folder of the machine's storage.
"""

from __future__ import annotations

import re
import unicodedata
from dataclasses import dataclass

from jobs.errors import ContractError, ErrorCode
from jobs.fleet.catalogue import ModelRow, Naming

MAX_NAME_CHARS = 255
MAX_PATH_CHARS = 1024
RESERVED_PREFIX = ".dncq-"  # dncq's own temporary files on a machine
# U+FFFD stands for bytes that were not UTF-8 (a %FF in the query): no real name has it;
# a lone surrogate (JSON's "\ud800") is no text at all.
_FORBIDDEN_IN_NAME = re.compile(r"[\x00-\x1f\x7f/\\:*?\"<>|\ufffd\ud800-\udfff]")
_UNSEEN = {"Cc", "Cf", "Zl", "Zp"}  # controls (C1 too), format and bidi marks, line breaks
_DRIVE = re.compile(r"^[A-Za-z0-9_]+:")
# Slashes that NFKC leaves as they are (Unicode's confusables of / and backslash).
_SLASH_LOOKALIKES = str.maketrans({"\u2044": "/", "\u2215": "/", "\u2571": "/", "\u29f8": "/",
                                   "\u2216": "\\", "\u2572": "\\", "\u29f5": "\\",
                                   "\u29f9": "\\"})
_FANUC_NUMBER = re.compile(r"[Oo]?([0-9]{1,8})")  # ASCII digits: \d also takes ١٠


def bad(status: str) -> ContractError:
    """A bad-parameter error saying what was wrong."""
    return ContractError(ErrorCode.BAD_PARAMETER, status)


class MissingParameter(ContractError):
    """A required parameter is absent: the request cannot be parsed (HTTP 400, per the contract)."""

    def __init__(self, name: str) -> None:
        super().__init__(ErrorCode.BAD_PARAMETER, f"{name} is required")


@dataclass(frozen=True)
class Root:
    """A root a machine's paths may start with."""

    display: str  # as the model writes it: //CNC_MEM/, TNC:\nc_prog, IC1, /nckfs, ""
    storage: str  # the transport's folder for it: CNC_MEM, TNC/nc_prog, IC1, nckfs, ""

    @classmethod
    def of(cls, display: str) -> Root:
        """The root written `display` in a model's notation."""
        folded = display.replace("\\", "/").replace(":", "")
        return cls(display, "/".join(p for p in folded.split("/") if p))

    @property
    def match_key(self) -> str:
        """Lower-case, `/`-separated, no trailing separator: what an input is compared with."""
        return self.display.replace("\\", "/").rstrip("/").lower()


@dataclass(frozen=True)
class Place:
    """A folder inside one of a machine's roots."""

    root: Root
    parts: tuple[str, ...] = ()

    @property
    def storage(self) -> str:
        """Path of this folder for the transport."""
        return "/".join(p for p in (self.root.storage, *self.parts) if p)

    def child(self, name: str) -> Place:
        """The subfolder `name` of this folder."""
        return Place(self.root, (*self.parts, name))

    def file(self, name: str) -> str:
        """Transport path of the file `name` in this folder."""
        return f"{self.storage}/{name}" if self.storage else name


class MachinePaths:
    """Path and name rules of one machine: its model row and its configured root."""

    def __init__(self, row: ModelRow, configured_root: str | None, *, confine: bool) -> None:
        """Args:
        row: the catalogue row that governs the machine.
        configured_root: the machine's `root`, or None for the row's default.
        confine: only the configured root is reachable (a file server in front of the
            machine); otherwise the model's own roots stay reachable beside it.
        """
        self.row = row
        own = [Root.of(r) for r in row.roots]
        self.roots = _longest_first(own)
        self.default = self._model_spelling(configured_root) if configured_root else own[0]
        if configured_root:
            others = [] if confine else [r for r in own if r != self.default]
            self.roots = _longest_first([self.default, *others])

    def _model_spelling(self, configured: str) -> Root:
        """A configured root that lies on one of the model's roots, written as the model writes
        it: `//memcard/` must reach the same storage folder as `//MEMCARD/`, and show as it."""
        folded = configured.replace("\\", "/")
        lowered = folded.lower()
        for root in self.roots:
            key = root.match_key
            if key and (lowered == key or lowered.startswith(key + "/")):
                place = Place(root, tuple(p for p in folded[len(key):].split("/") if p))
                return Root(self.display(place), place.storage)
        return Root.of(configured)

    # -- folders -----------------------------------------------------------

    def resolve(self, dir_at_cnc: str | None, sub_dir: str | None) -> Place:
        """The folder a request names (the contract's rules for paths)."""
        if dir_at_cnc and not dir_at_cnc.strip("/\\"):
            # "/" alone: a root written so (a Mock's), else the folder readAllPrograms calls
            # "/" (2.6.15), the default root, on every model
            return Place(next((r for r in self.roots if not r.match_key), self.default))
        if not self.row.target_folder and (dir_at_cnc or sub_dir):
            raise ContractError(ErrorCode.UNSUPPORTED, f"{self.row.name} takes no target folder")
        if dir_at_cnc:
            return self.parse(dir_at_cnc)
        if sub_dir:
            return Place(self.default, self._relative(sub_dir))
        return Place(self.default)

    def parse(self, text: str) -> Place:
        """A folder written as rooted (taken as written) or relative (to the default root)."""
        _check_length(text)
        folded = text.replace("\\", "/")
        lowered = folded.lower()
        for root in self.roots:
            key = root.match_key
            if not key and not folded.startswith("/"):
                continue
            if lowered == key or lowered.startswith(key + "/") or (key == "" and folded):
                return Place(root, self._relative(folded[len(key):]))
        if folded.startswith("/") or _DRIVE.match(folded):
            raise ContractError(
                ErrorCode.PATH_OUTSIDE_ROOT,
                f"{text!r} is not below this machine's roots ({', '.join(self.root_names())})",
            )
        return Place(self.default, self._relative(folded))

    def _relative(self, text: str) -> tuple[str, ...]:
        _check_length(text)
        parts = tuple(p for p in re.split(r"[\\/]+", text) if p not in ("", "."))
        for part in parts:
            if ".." in re.split(r"[\\/]", reads_as(part)):  # `..`, and `．．` or `‥` that read so
                raise ContractError(ErrorCode.PATH_OUTSIDE_ROOT,
                                    f"'..' is not allowed in a path ({text!r})")
            check_name(part, what="folder name")
        return parts

    def display(self, place: Place) -> str:
        """The folder in the model's own notation."""
        sep = self.row.separator
        shown = place.root.display
        if place.parts:
            if shown and not shown.endswith(("/", "\\")):
                shown += sep
            shown += sep.join(place.parts)
        return shown

    def relative_display(self, parts: tuple[str, ...]) -> str:
        """A folder relative to a requested one; `/` for that folder itself (2.6.15)."""
        return self.row.separator.join(parts) if parts else "/"

    def root_names(self) -> list[str]:
        """The roots, as the model writes them."""
        return [r.display or "(unnamed)" for r in self.roots]

    # -- file names --------------------------------------------------------

    def stored_name(self, file_name: str | None) -> str:
        """The name a request's `fileName` has in the machine's storage."""
        if not file_name:
            raise MissingParameter("fileName")
        check_name(file_name)
        if self.row.is_fanuc and (m := _FANUC_NUMBER.fullmatch(file_name)):
            return fanuc_program(int(m.group(1)))
        if self.row.needs_extension and not re.search(r"\.[^.]+$", file_name):
            raise bad(f"{self.row.name} needs the extension in fileName (e.g. {file_name}.MPF)")
        return file_name

    def listed_name(self, stored: str) -> str:
        """The name a listing shows for a stored file (Fanuc drops O and leading zeros)."""
        if self.row.naming is Naming.FANUC_STANDARD and (m := re.fullmatch(r"O([0-9]+)", stored)):
            return str(int(m.group(1)))
        return stored


def _longest_first(roots: list[Root]) -> list[Root]:
    # So that TNC:\nc_prog wins over TNC:\ and /nckfs over /.
    return sorted(roots, key=lambda r: len(r.match_key), reverse=True)


def fanuc_program(number: int) -> str:
    """The standard Fanuc program name for a number: O and at least four digits."""
    if number == 0:  # a control stores none: its numbers start at 1
        raise bad("O0000 is not a program number (Fanuc programs are O0001 to O99999999)")
    return f"O{number:04d}"


def fanuc_name_from_content(head: bytes) -> str:
    """The program name of Fanuc content: the text between its first and second newline.

    A leading `%` line is the usual first line; content that starts straight with
    the program line (no `%`) is read from its first line instead.
    """
    lines = head.split(b"\n")
    candidates = [lines[1]] if len(lines) > 2 else []
    candidates.append(lines[0])
    for raw in candidates:
        line = raw.decode("latin-1").strip()
        if m := re.match(r"^[Oo]([0-9]{1,8})\b", line):
            return fanuc_program(int(m.group(1)))
        if m := re.match(r"^<([^<>]+)>", line):  # 30i-style named program: <SAMPLE>
            check_name(m.group(1))
            return m.group(1)
    raise bad("no program name between the first and second line of the content (e.g. O1234)")


def reads_as(text: str) -> str:
    """What `text` reads as: NFKC (`．．／` is `../`, `‥` is `..`), slash look-alikes as slashes.

    A far side or a tool on the way (Windows' best-fit code pages) may fold the one into the
    other, so the path rules are checked on this form too.
    """
    return unicodedata.normalize("NFKC", text).translate(_SLASH_LOOKALIKES)


def check_name(name: str, *, what: str = "fileName") -> None:
    """Refuse a name that is a path, reserved, or unsafe on any storage, also as it reads."""
    _check_plain(name, what)
    read = reads_as(name)
    if read != name:
        try:
            _check_plain(read, what, length=False)  # NFKC may lengthen: ﬁ is fi
        except ContractError:
            raise bad(f"{what} {name!r} reads as {read!r}, which is not a plain name") from None


def _check_plain(name: str, what: str, *, length: bool = True) -> None:
    if name in (".", ".."):
        raise bad(f"{what} {name!r} is not a name")  # contract: a name, never a path step
    if length and len(name) > MAX_NAME_CHARS:
        raise bad(f"{what} is longer than {MAX_NAME_CHARS} characters")
    if m := _FORBIDDEN_IN_NAME.search(name):
        raise bad(f"{what} must be a plain name; {m.group()!r} is not allowed")
    if unseen := next((c for c in name if unicodedata.category(c) in _UNSEEN), None):
        # A name must read as what it is: a right-to-left override shows the rest of a
        # name backwards, and a zero-width space makes two names that look the same.
        raise bad(f"{what} must be a plain name; {unseen!r} (a control or invisible "
                  "character) is not allowed")
    if name.startswith(RESERVED_PREFIX):
        raise bad(f"{what} may not start with {RESERVED_PREFIX!r}")
    if name != name.strip():
        raise bad(f"{what} may not start or end with spaces")


def _check_length(text: str) -> None:
    if len(text) > MAX_PATH_CHARS:
        raise bad(f"path is longer than {MAX_PATH_CHARS} characters")
    if "\x00" in text:
        raise bad("path contains a NUL byte")
