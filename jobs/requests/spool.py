"""What a machine sent over its link, kept on disk from the moment it is read until its job
is recorded: a worker killed in between leaves it to the machine's next listener.

One file per program in `<data_dir>/requests/spool/<machine>/`, written under a temporary
name, flushed to the disk and renamed, so that a file there is always whole. Its id is the
id of the job that records it: a program whose job was recorded before its file was removed
is seen as recorded, not recorded twice. Only regular files of the folder are read: a
symlink, a FIFO or a device named like one is left where it is, as a damaged file is.
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import os
import stat
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from jobs.folders import private_dir, private_opener
from jobs.settings import Settings

SUFFIX = ".json"

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Spooled:
    """One program read from a machine's link and not yet known to be recorded."""

    id: str  # the id of the job that records it
    text: bytes
    broken_off: str | None  # why its reception broke off (kept as failed); None: whole
    path: Path  # named by `read_ns`, so that programs are taken up in their order
    read_ns: int  # when it was read from the link (time.time_ns())

    @property
    def kept_s(self) -> float:
        """How long ago it was read from the link."""
        return max(0.0, time.time() - self.read_ns / 1e9)


def _folder(settings: Settings, machine_id: str) -> Path:
    return settings.data_dir / "requests" / "spool" / machine_id


def put(settings: Settings, machine_id: str, text: bytes, *,
        broken_off: str | None = None) -> Spooled:
    """Keep what the machine sent on the disk before anything else is done with it."""
    folder = _folder(settings, machine_id)
    for level in (folder.parent.parent, folder.parent, folder):  # each one 0700
        private_dir(level)
    entry_id, read_ns = uuid.uuid4().hex[:16], time.time_ns()
    path = folder / f"{read_ns:020d}-{entry_id}{SUFFIX}"
    temp = folder / f".{entry_id}.tmp"
    body = json.dumps({"id": entry_id, "brokenOff": broken_off,
                       "text": base64.b64encode(text).decode("ascii")})
    try:
        with open(temp, "w", opener=private_opener) as out:
            out.write(body)
            out.flush()
            os.fsync(out.fileno())
        os.replace(temp, path)
    except BaseException:
        # A disk full midway: the part written would take the space of the next one.
        with contextlib.suppress(OSError):
            temp.unlink()
        raise
    try:
        _sync_folder(folder)  # the rename itself survives a crash of the host
    except OSError as exc:
        # The file is in place for every process all the same: handled under its id, it is
        # not recorded a second time by a later listener that finds it. Only a crash of the
        # host before the folder reaches the disk could still lose it.
        log.warning("the spool folder %s could not be flushed to the disk (%s)", folder, exc)
    return Spooled(entry_id, text, broken_off, path, read_ns)


def pending(settings: Settings, machine_id: str) -> list[Spooled]:
    """The machine's programs kept and not yet removed, oldest first; a file that cannot be
    read (another program's, or damaged by hand) is left where it is.

    Raises:
        OSError: the machine's folder is there but cannot be listed (not a folder, or
            another user's).
    """
    folder = _folder(settings, machine_id)
    try:
        paths = sorted(p for p in folder.iterdir() if p.name.endswith(SUFFIX))
    except FileNotFoundError:
        return []
    found = []
    for path in paths:
        try:
            raw = json.loads(_read_regular(path))
            found.append(Spooled(str(raw["id"]), base64.b64decode(raw["text"]),
                                 raw.get("brokenOff"), path,
                                 read_ns=int(path.name.partition("-")[0])))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return found


def _read_regular(path: Path) -> bytes:
    """The content of `path` if it is a regular file; OSError otherwise (a FIFO would wait
    for a writer forever, and a symlink may lead anywhere)."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    with os.fdopen(fd, "rb") as source:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(f"{path} is not a regular file")
        return source.read()


def remove(entry: Spooled) -> None:
    """Forget a program whose job is recorded."""
    with contextlib.suppress(FileNotFoundError):
        entry.path.unlink()


def _sync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
