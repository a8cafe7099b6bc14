"""Controller models and file-server types: the contract's tables 55, 56 and 57 as data.

One row per model; adding a model is adding a row to `ROWS`. Model names are
matched forgivingly: case, spaces, dashes and brackets do not matter, and a
brand with a catch-all row ("Fanuc (other models)") takes any model of that
brand that has no row of its own.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from enum import StrEnum


class Naming(StrEnum):
    """How a model names its programs."""

    PLAIN = "plain"  # the name is the file name
    FANUC = "fanuc"  # name taken from the content on send; O-number spellings accepted
    FANUC_STANDARD = "fanuc_standard"  # FANUC, and listings drop the O and leading zeros


@dataclass(frozen=True)
class ModelRow:
    """What one controller model or file-server type allows.

    Attributes:
        name: canonical display name.
        server_type: the table's "file server type" column ("machine storage" for a controller).
        default_root: root in the model's notation; "" for a single unnamed folder.
        other_roots: further roots a `dirAtCNC` or the machine's `root` may point at.
        separator: folder separator of the model's notation.
        target_folder: table 55: may a request name a folder at all.
        list_subdirs: table 56: does a listing return subfolders.
        make_dirs: table 57: can folders be created and removed.
        make_dirs_roots: if set, folders may only be created/removed below these roots.
        needs_extension: `fileName` must carry an extension (Gsk, Siemens, ...).
        naming: program naming rules.
        select_program: 2.6.14 supported.
        select_is_noop: selectProgram answers success and changes nothing (the Mock model).
        lock_range: 2.6.10 supported.
        aliases: further spellings that name this row.
        brand_catch_all: this row takes any model of `brand` without a row of its own.
    """

    name: str
    server_type: str = "machine storage"
    default_root: str = "/"
    other_roots: tuple[str, ...] = ()
    separator: str = "/"
    target_folder: bool = True
    list_subdirs: bool = True
    make_dirs: bool = True
    make_dirs_roots: tuple[str, ...] | None = None
    needs_extension: bool = False
    naming: Naming = Naming.PLAIN
    select_program: bool = False
    select_is_noop: bool = False
    lock_range: bool = False
    aliases: tuple[str, ...] = ()
    brand_catch_all: str | None = None
    notes: str = field(default="", compare=False)

    @property
    def roots(self) -> tuple[str, ...]:
        """Every root this model accepts, the default first."""
        return (self.default_root, *self.other_roots)

    @property
    def is_fanuc(self) -> bool:
        """Fanuc naming rules apply."""
        return self.naming in (Naming.FANUC, Naming.FANUC_STANDARD)


_FANUC_LISTED = ("0i-D", "0i-F", "30i", "31i", "32i", "35i", "Power Motion i-A")


def _fanuc_listed(model: str) -> ModelRow:
    # 0i-D is the one listed model without the memory-card root (table 55, note ★).
    card = () if model == "0i-D" else ("//MEMCARD/",)
    # The 0i series is sold as mill (M) and lathe (T) variants: 0i-MF, 0i-TD, ...
    variants = tuple(f"Fanuc 0i-{kind}{model[-1]}" for kind in "MT") if model[:3] == "0i-" else ()
    return ModelRow(
        name=f"Fanuc {model}",
        default_root="//CNC_MEM/",
        other_roots=card,
        naming=Naming.FANUC_STANDARD,
        select_program=True,
        lock_range=True,
        aliases=(f"Fanuc Series {model}", *variants),
    )


ROWS: tuple[ModelRow, ...] = (
    ModelRow(name="Brother TC", target_folder=False, make_dirs=False, select_program=True),
    ModelRow(name="Brother S", select_program=True),
    ModelRow(name="Delta", default_root="B:\\", separator="\\", list_subdirs=False),
    ModelRow(
        name="Fagor", default_root="MEMORY", list_subdirs=False, make_dirs=False,
        brand_catch_all="fagor",
    ),
    *(_fanuc_listed(m) for m in _FANUC_LISTED),
    ModelRow(
        name="Fanuc (other models)",
        default_root="//CNC_MEM/",  # the machine's foreground folder; a mock uses CNC_MEM
        target_folder=False,
        list_subdirs=False,
        make_dirs=False,
        naming=Naming.FANUC,
        lock_range=True,
        brand_catch_all="fanuc",
    ),
    ModelRow(
        name="Gsk 980", default_root="/user/NCPROG", list_subdirs=False, make_dirs=False,
        needs_extension=True, aliases=("GSK 988",), brand_catch_all="gsk",
    ),
    ModelRow(name="Haas", default_root="", list_subdirs=False, brand_catch_all="haas",
             aliases=("Haas MT-CONNECT",)),
    ModelRow(
        name="Heidenhain TNC640", default_root="TNC:\\nc_prog", other_roots=("TNC:\\",),
        separator="\\", needs_extension=True, aliases=("Heidenhain TNC640 DNC",),
    ),
    ModelRow(
        name="Heidenhain iTNC530", default_root="TNC:\\", separator="\\", needs_extension=True,
        brand_catch_all="heidenhain",
    ),
    ModelRow(name="Lynuc", default_root="/home/Lynuc/Users/NCFiles", make_dirs=False,
             brand_catch_all="lynuc"),
    *(
        ModelRow(
            name=f"Mitsubishi {series}",
            default_root="PRG\\USER\\",
            other_roots=("IC1",),
            separator="\\",
            list_subdirs=False,
            make_dirs_roots=("IC1",),
            lock_range=True,
            aliases=(f"Mitsubishi {series[:3]}",),  # M70 shares the M700 row, M80 the M800
        )
        for series in ("M700", "M800")
    ),
    ModelRow(
        name="Mitsubishi",
        default_root="PRG\\USER\\",
        separator="\\",
        list_subdirs=False,
        make_dirs=False,
        lock_range=True,
        brand_catch_all="mitsubishi",
    ),
    ModelRow(name="Mock", select_program=True, select_is_noop=True, aliases=("Mock machine",)),
    ModelRow(name="Okuma", default_root="MD1", brand_catch_all="okuma", needs_extension=True),
    ModelRow(name="Rexroth OPC UA", default_root="Filesystem/prog", brand_catch_all="rexroth"),
    ModelRow(name="Siemens", default_root="/nckfs", needs_extension=True,
             brand_catch_all="siemens", aliases=("Siemens generic", "Sinumerik")),
    ModelRow(name="Siemens OPC UA", default_root="Sinumerik/FileSystem/PartProgram",
             needs_extension=True),
    ModelRow(name="Siemens 840D", default_root="mpf.dir", needs_extension=True,
             aliases=("Siemens 810D", "Siemens 810D/840D", "Sinumerik 840D")),
    ModelRow(name="Other", default_root="", target_folder=False, list_subdirs=False,
             make_dirs=False, aliases=("other model",)),
    # File servers in front of a machine: their own row governs (the contract's rules for paths).
    ModelRow(name="FTP server", server_type="FTP server", aliases=("FTP",)),
    ModelRow(name="Shared folder", server_type="shared folder", default_root="",
             aliases=("share", "SMB")),
    ModelRow(name="Shared folder (Win XP)", server_type="shared folder (Win XP)",
             default_root=""),
    ModelRow(name="Wireless transfer box", server_type="wireless transfer box"),
    ModelRow(name="Gateway file server", server_type="gateway file server",
             aliases=("gateway",)),
    ModelRow(name="OctoPrint", server_type="printer host"),
    ModelRow(name="Moonraker", server_type="printer host", aliases=("Klipper",)),
)


class UnknownModel(ValueError):
    """No row of the catalogue matches this model name."""


def _key(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


def _index() -> dict[str, ModelRow]:
    index: dict[str, ModelRow] = {}
    for row in ROWS:
        for spelling in (row.name, *row.aliases):
            index.setdefault(_key(spelling), row)
    return index


_BY_KEY = _index()
_CATCH_ALL = {row.brand_catch_all: row for row in ROWS if row.brand_catch_all}


def lookup(model: str) -> ModelRow:
    """The row for `model`, matched forgivingly.

    Raises:
        UnknownModel: no row and no brand catch-all matches.
    """
    key = _key(model)
    if key in _BY_KEY:
        return _BY_KEY[key]
    # A variant of a known model ("Mitsubishi M700L", "Fanuc 0i-F Plus"): the longest
    # row key the name starts with.
    prefixes = [k for k in _BY_KEY if key.startswith(k)]
    if prefixes:
        return _BY_KEY[max(prefixes, key=len)]
    for brand, row in _CATCH_ALL.items():
        if key.startswith(brand):
            return row
    known = ", ".join(row.name for row in ROWS)
    raise UnknownModel(f"unknown controller model {model!r}; known models: {known}")


def names() -> list[str]:
    """Every canonical model name, in table order."""
    return [row.name for row in ROWS]
