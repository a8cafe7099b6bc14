"""Safe, reversible archive names for machine names and machine paths.

Every path component is percent-encoded outside a safe set: `/`, `\\`, `:`, `%`, `@`,
control characters and the names `.` and `..` can never reach the archive as written,
so no entry can climb out of its folder (no zip-slip) and two different paths never
share a name. `urllib.parse.unquote` gives the original back. Non-ASCII letters stay
as they are (UTF-8, flagged in the ZIP).

Layout of one machine's folder: paths below the machine's default root as they are;
paths below another root of its model under `@<root>` (`//MEMCARD/PRG` becomes
`@MEMCARD/PRG`, `IC1\\100` becomes `@IC1/100`). A real folder named `@x` is written
`%40x`, so the two cannot meet.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any
from urllib.parse import quote

MANIFEST_NAME = "_manifest.json"  # machine folders start with a letter or digit: no clash
ROOT_MARK = "@"
_SAFE = " !#$&'()+,;=[]^_`{}~-."  # kept as written besides letters and digits


def component(name: str) -> str:
    """One path component as an archive name component."""
    if name in (".", ".."):
        return name.replace(".", "%2E")
    return quote(name, safe=_SAFE)


def backup_name(when: datetime) -> str:
    """`BackupFiles_<YYYY.MM.DD.HH.MM.SS>`: the contract's top folder, and the stored ZIP's name."""
    return f"BackupFiles_{when.strftime('%Y.%m.%d.%H.%M.%S')}"


def manifest_file(path: str, archive_path: str, size: int, mtime: float | None,
                  sha256: str) -> dict[str, Any]:
    """One file's entry in the manifest."""
    return {"path": path, "archivePath": archive_path, "size": size, "mtime": mtime,
            "sha256": sha256}


def machine_folder(machine_id: str, machine_name: str) -> str:
    """`<machineID>_<machineName>`, the contract's folder for one machine."""
    return f"{component(machine_id)}_{component(machine_name)}"


def file_path(root_storage: str | None, parts: tuple[str, ...], name: str) -> str:
    """A machine file's path inside its machine folder.

    Args:
        root_storage: storage path of a root other than the machine's default, or None.
        parts: folders from that root down to the file.
        name: the file's name on the machine.
    """
    encoded = [component(p) for p in (*parts, name)]
    if root_storage:
        encoded.insert(0, ROOT_MARK + "/".join(component(p) for p in root_storage.split("/")))
    return "/".join(encoded)
