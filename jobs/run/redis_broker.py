"""kombu's Redis transport, with one redis-py client per channel instead of one per command.

kombu's Redis channel builds a new `redis.Redis` for every publish, every delivery's
unacked bookkeeping and every ack made away from its polling connection. Building one
costs about 0.13 ms of Python (its table of response callbacks), which on a worker
running hundreds of short tasks is time the interpreter lock is held for nothing. A
client is safe to share between threads: each command or pipeline takes a connection
from the channel's pool and gives it back. Selected with Celery's `broker_transport`
setting when the broker URL is a Redis one (see jobs.run.queue).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from kombu.transport import redis


class Channel(redis.Channel):
    """A Redis channel that reuses one client for the commands not made while polling."""

    _shared_client: Any = None

    @contextlib.contextmanager
    def conn_or_acquire(self, client: Any = None) -> Iterator[Any]:
        if client:
            yield client
            return
        shared = self._shared_client
        if shared is None or shared.connection_pool is not self.pool:  # a new pool after close
            shared = self._shared_client = self._create_client()
        yield shared


class Transport(redis.Transport):
    """kombu's Redis transport with `Channel` above."""

    Channel = Channel
