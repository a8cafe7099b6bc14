"""kombu's filesystem transport, with messages that appear in the queue folder only whole.

kombu's filesystem channel creates a message file under its final name and then writes
it, while a consumer takes any file with that name pattern by moving it away, without
the lock the producer holds. A consumer polling at that moment reads an empty file: the
message is lost, and Celery's consumer stops on the JSON error (the embedded worker of
`dncq serve` went down that way). Here a message is written under a name no consumer
looks at and renamed into place, which is atomic within the folder. Selected with
Celery's `broker_transport` setting in the embedded mode (see jobs.queue).
"""

from __future__ import annotations

import os
import uuid
from time import monotonic
from typing import Any

from kombu.exceptions import ChannelError
from kombu.transport import filesystem
from kombu.utils.json import dumps


class Channel(filesystem.Channel):
    """A filesystem channel whose messages are renamed into place once written."""

    def _put(self, queue: str, payload: Any, **kwargs: Any) -> None:  # type: ignore[override]
        name = f"{round(monotonic() * 1000)}_{uuid.uuid4()}.{queue}.msg"  # kombu's own names
        final = os.path.join(self.data_folder_out, name)
        writing = os.path.join(self.data_folder_out, f".{name}.part")  # not a message name
        try:
            with open(writing, "wb") as f:
                f.write(dumps(payload).encode())
            os.replace(writing, final)
        except OSError as exc:
            raise ChannelError(f"Cannot add file {final!r} to directory") from exc


class Transport(filesystem.Transport):
    """kombu's filesystem transport with `Channel` above."""

    Channel = Channel
