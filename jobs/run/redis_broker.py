"""kombu's Redis transport, with one redis-py client per channel instead of one per command,
and channels that outlive their connection's close.

kombu's Redis channel builds a new `redis.Redis` for every publish made away from its
polling connection (and, with its acknowledgement emulation, which jobs.run.queue turns
off, for every delivery's unacked bookkeeping and every ack). Building one
costs about 0.13 ms of Python (its table of response callbacks), which on a worker
running hundreds of short tasks is time the interpreter lock is held for nothing. A
client is safe to share between threads: each command or pipeline takes a connection
from the channel's pool and gives it back. Selected with Celery's `broker_transport`
setting when the broker URL is a Redis one (see jobs.run.queue).

When Redis goes away, Celery's consumer collects its connection: kombu closes the
channels one by one, and the first whose close fails (with the emulation on, it restores
unacknowledged messages to a Redis that is not there) leaves the others open, then detaches
the transport from its connection. Closing one of those later (or acking, or publishing
through it) builds a new pool from the connection's address, which is gone:
`AttributeError: 'NoneType' object has no attribute 'hostname'`, which Celery does not
count as a connection error, so the worker exits. A channel here keeps the address it was made with.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from kombu.transport import redis
from redis import exceptions as redis_errors


class Channel(redis.Channel):
    """A Redis channel that reuses one client for the commands not made while polling,
    and that can still reach Redis after its connection was closed."""

    _shared_client: Any = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._known_params: dict[bool, dict[str, Any]] = {}
        super().__init__(*args, **kwargs)  # pings Redis: the asynchronous pool's address
        self._connparams(asynchronous=False)  # kept for a pool made after the close

    def _connparams(self, asynchronous: bool = False) -> dict[str, Any]:
        connection = self.connection  # the transport; None once the channel is closed
        if connection is not None and connection.client is not None:
            params: dict[str, Any] = super()._connparams(asynchronous=asynchronous)
            self._known_params[asynchronous] = params
            return dict(params)
        known = self._known_params.get(asynchronous)
        if known is None:  # a connection error: kombu and Celery reconnect on those
            raise redis_errors.ConnectionError("the broker connection was closed")
        return dict(known)

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
