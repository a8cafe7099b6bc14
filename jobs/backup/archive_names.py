"""Safe, reversible archive names for machine names and machine paths.

Every path component is written as it is but for what cannot be in a ZIP name safely,
which is percent-encoded as UTF-8: `/`, `\\`, `%`, `@`, the characters Windows refuses
in a name (`"*:<>?|`), control and format characters, and the names `.` and `..`. So no
entry can climb out of its folder (no zip-slip) and two different paths never share a
name; `urllib.parse.unquote` gives the original back, but for a name cut short to 255 bytes
(`fitted`). Letters outside ASCII stay as they are (UTF-8 names, flagged as such in the ZIP,
which every current unzip reads).

Layout of one machine's folder: paths below the machine's default root as they are;
paths below another root of its model under `@<root>` (`//MEMCARD/PRG` becomes
`@MEMCARD/PRG`, `IC1\\100` becomes `@IC1/100`). A real folder named `@x` is written
`%40x`, so the two cannot meet.
"""

from __future__ import annotations

import hashlib
import re
import unicodedata
from collections.abc import Sequence
from datetime import datetime
from typing import Any

MANIFEST_NAME = "_manifest.json"  # machine folders start with a letter or digit: no clash
ROOT_MARK = "@"
_ENCODED_ASCII = frozenset('"%*/:<>?@\\|')  # separators, the escape, the root mark, Windows
# Control, format (bidi overrides, zero-width), surrogates, unassigned, line separators.
_ENCODED_CATEGORIES = frozenset({"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"})
NAME_MAX_BYTES = 255  # of one name, in UTF-8, on the file systems unzip writes to (ext4, APFS)
CUT_MARK = "~{:.8}"  # after a name cut short: 8 hex digits of the whole name's SHA-256


def component(name: str) -> str:
    """One path component as an archive name component."""
    if name in (".", ".."):
        return name.replace(".", "%2E")
    return "".join(c if _kept(c) else _escaped(c) for c in name)


def fitted(name: str, *, room: int = NAME_MAX_BYTES) -> str:
    """An archive name component as it is when its UTF-8 takes at most `room` bytes; else
    cut short on a character (never inside a `%XX`) and marked with its SHA-256, so that
    two long names that begin alike stay apart. The manifest's `path` keeps the original."""
    whole = name.encode()
    if len(whole) <= room:
        return name
    mark = CUT_MARK.format(hashlib.sha256(whole).hexdigest())
    head = whole[:room - len(mark)].decode("utf-8", "ignore")
    return re.sub(r"%[0-9A-F]?$", "", head) + mark


def _kept(c: str) -> bool:
    if c.isascii():
        return c.isprintable() and c not in _ENCODED_ASCII
    return unicodedata.category(c) not in _ENCODED_CATEGORIES


def _escaped(c: str) -> str:
    """`%XX` of each UTF-8 byte (a lone surrogate as the bytes it stands for)."""
    return "".join(f"%{b:02X}" for b in c.encode("utf-8", "surrogatepass"))


def backup_name(when: datetime) -> str:
    """`BackupFiles_<YYYY.MM.DD.HH.MM.SS>`: the contract's top folder (a stored ZIP's name
    starts with it)."""
    return f"BackupFiles_{when.strftime('%Y.%m.%d.%H.%M.%S')}"


def manifest_file(path: str, archive_path: str, size: int, mtime: float | None,
                  sha256: str) -> dict[str, Any]:
    """One file's entry in the manifest."""
    return {"path": path, "archivePath": archive_path, "size": size, "mtime": mtime,
            "sha256": sha256}


def machine_folder(machine_id: str, machine_name: str, *, room: int = NAME_MAX_BYTES) -> str:
    """`<machineID>_<machineName>`, the contract's folder for one machine; a name too long
    for `room` bytes is cut short (`fitted`), the id (at most 64 characters) kept whole."""
    return fitted(f"{component(machine_id)}_{component(machine_name)}", room=room)


def machine_folders(machines: Sequence[tuple[str, str]]) -> list[str]:
    """The folder of each (id, name) in one backup, in order: `machine_folder`, and for a
    machine whose folder an earlier one took (an id with `_` in it: `5_1` named `X` and `5`
    named `1_X` are both `5_1_X`), the same with `~2` (`~3`, ...) after it. Two machines
    never share a folder, so none of their files takes another's name."""
    folders: list[str] = []
    used: set[str] = set()
    for machine_id, machine_name in machines:
        folder, n = machine_folder(machine_id, machine_name), 1
        while folder in used:
            n += 1
            room = NAME_MAX_BYTES - len(f"~{n}")
            folder = f"{machine_folder(machine_id, machine_name, room=room)}~{n}"
        used.add(folder)
        folders.append(folder)
    return folders


def file_path(root_storage: str | None, parts: tuple[str, ...], name: str) -> str:
    """A machine file's path inside its machine folder.

    Args:
        root_storage: storage path of a root other than the machine's default, or None.
        parts: folders from that root down to the file.
        name: the file's name on the machine.
    """
    encoded = [fitted(component(p)) for p in (*parts, name)]
    if root_storage:
        encoded.insert(0, ROOT_MARK + "/".join(component(p) for p in root_storage.split("/")))
    return "/".join(encoded)
