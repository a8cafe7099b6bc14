"""kombu's filesystem transport, with messages that appear in the queue folder only whole.

kombu's filesystem channel creates a message file under its final name and then writes
it, while a consumer takes any file with that name pattern by moving it away, without
the lock the producer holds. A consumer polling at that moment reads an empty file: the
message is lost, and Celery's consumer stops on the JSON error (the embedded worker of
`dncq serve` went down that way). Here a message is written under a name no consumer
looks at and renamed into place, which is atomic within the folder. A write that fails
removes its part; the part of a process killed mid-write is removed by the first channel
a later process opens on the folder. Selected with Celery's `broker_transport` setting
in the embedded mode (see jobs.run.queue).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import uuid
from typing import Any

from kombu.exceptions import ChannelError
from kombu.transport import filesystem
from kombu.utils.json import dumps

from jobs.folders import private_opener

PART_SUFFIX = ".part"
STALE_PART_S = 3600.0  # a message is written in milliseconds: a part this old lost its writer

_swept: set[str] = set()  # folders this process has cleared of stale parts

log = logging.getLogger(__name__)


class Channel(filesystem.Channel):
    """A filesystem channel whose messages are renamed into place once written."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        folder = self.data_folder_out
        if folder not in _swept:
            _swept.add(folder)
            if removed := remove_stale_parts(folder):
                log.warning("removed %d half-written messages of dead writers from %s",
                            removed, folder)

    def _put(self, queue: str, payload: Any, **kwargs: Any) -> None:  # type: ignore[override]
        name = f"{round(time.monotonic() * 1000)}_{uuid.uuid4()}.{queue}.msg"  # kombu's own names
        final = os.path.join(self.data_folder_out, name)
        writing = os.path.join(self.data_folder_out, f".{name}{PART_SUFFIX}")  # not a message
        try:
            with open(writing, "wb", opener=private_opener) as f:
                f.write(dumps(payload).encode())
            os.replace(writing, final)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.unlink(writing)
            raise ChannelError(f"Cannot add file {final!r} to directory") from exc


def remove_stale_parts(folder: str, older_than_s: float = STALE_PART_S) -> int:
    """Delete message parts left by writers that died mid-write; returns how many."""
    removed = 0
    cutoff = time.time() - older_than_s
    with contextlib.suppress(FileNotFoundError), os.scandir(folder) as entries:
        for entry in entries:
            if not (entry.name.startswith(".") and entry.name.endswith(PART_SUFFIX)):
                continue
            with contextlib.suppress(FileNotFoundError):
                if entry.stat().st_mtime < cutoff:
                    os.unlink(entry.path)
                    removed += 1
    return removed


class Transport(filesystem.Transport):
    """kombu's filesystem transport with `Channel` above."""

    Channel = Channel
