"""Half-written files that name their writer (host and process), and the sweep of those a
writer on this host left behind when it was killed mid-write.

A writer removes its own part when it fails; only SIGKILL (or a host that went down)
leaves one. Its name says whether its writer may be at it: a process of this host that no
longer runs will not finish it (a large backup is written for minutes, so age alone would
not tell). A part nobody wrote to for `STILL_WRITING_S` is not taken for one being
written (a writer of another host cannot be asked; a pid may since be another process's),
though only those of this host's ended processes are removed.
"""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

WRITER = socket.gethostname().replace("-", "_")  # "-" separates the name's fields


def part_name(prefix: str, rest: str) -> str:
    """A part's name: `prefix`, this host and process, then `rest`."""
    return f"{prefix}{WRITER}-{os.getpid()}-{rest}"


def remove_parts_of_dead_writers(folder: Path, prefix: str) -> int:
    """Delete the parts named by `part_name(prefix, …)` in `folder` whose writer was a
    process of this host that has ended; returns how many. Other hosts' are left alone."""
    mine = f"{prefix}{WRITER}-"
    with os.scandir(folder) as entries:
        found = [entry.name for entry in entries if entry.name.startswith(mine)]
    removed = 0
    for name in found:
        pid = name[len(mine):].split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            (folder / name).unlink(missing_ok=True)
            removed += 1
    return removed


def others_writing(folder: Path, prefix: str, marker: str, *, besides: str) -> bool:
    """Whether a part named by `part_name(prefix, …)` in `folder`, with `marker` in its name
    and other than `besides` (the caller's own), is still being written: its writer a live
    process of this host (this one too: its other threads) or one of another host (which
    cannot be asked), and the part written to within `STILL_WRITING_S`."""
    here = f"{prefix}{WRITER}-"
    recent = time.time() - STILL_WRITING_S
    with os.scandir(folder) as entries:
        found = [entry for entry in entries if entry.name.startswith(prefix)
                 and marker in entry.name and entry.name != besides]
    for entry in found:
        name = entry.name
        try:
            if entry.stat().st_mtime < recent:
                continue  # a writer killed on another host, or one whose pid is now another's
        except FileNotFoundError:  # placed, or given up, since the folder was read: its
            return True  # writer registers the job, or records why it could not
        pid = name[len(here):].split("-", 1)[0] if name.startswith(here) else None
        if pid is None or not pid.isdigit() or _alive(int(pid)):
            return True
    return False


# A writer writes without pause (a backup's ZIP: pieces of 256 KB); a part untouched this
# long has none, whatever its name says.
STILL_WRITING_S = 600.0


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True
