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

kombu takes one message per BRPOP, a round trip and a poll of its socket each. When a BRPOP
returns a message, a channel here also takes what else waits in the same list, up to what
the consumer may still hold (its prefetch window) and `TAKE_MORE`, in one RPOP with a count.

In a worker, a channel holds no more unfinished messages than its pool can start
(`take_in_bulk_up_to`): neither the bulk take nor the BRPOP goes past it. While the pool is
full, the poller waits for an acknowledgement (a task ended) instead of kombu's sleep of up
to a second, and then polls again.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Iterator
from queue import Empty
from typing import Any

from kombu.transport import redis, virtual
from kombu.utils.encoding import bytes_to_str
from kombu.utils.json import loads
from redis import exceptions as redis_errors

log = logging.getLogger(__name__)

TAKE_MORE = 16  # messages taken in one round trip after a BRPOP returned one
FULL_POOL_WAIT_S = 1.0  # at most, between two looks at a full pool (kombu's own sleep)
# At most, between two looks of a worker whose every operation slot is busy: what it takes
# then waits for a slot of its own (claimed ahead), so the workers with room look first.
CLAIM_AHEAD_WAIT_S = 0.05
_pool_size: int | None = None  # a worker's: the tasks it runs at once
_slots: int | None = None  # a worker's machine operations at once, where its pool claims ahead


def take_in_bulk_up_to(pool_size: int | None, *, slots: int | None = None) -> None:
    """Take more messages after a BRPOP only while this process holds fewer unfinished tasks
    than `slots` (a worker's operation slots, where its pool is larger and claims ahead of
    them) or `pool_size` (its pool; None: no such bound). With every slot busy, look again
    once a task ended or CLAIM_AHEAD_WAIT_S passed, and then take up to the pool: what is
    still queued by then, no worker with room took (and where tasks end often, the queue
    is longer than the workers' slots, and none has room).

    Taken beyond its slots at once, a message waits until one of the worker's operations
    ends, while another worker may have room: with two workers of 32 slots sharing a
    50-machine backup, one of them now and then held more machines than it could start, and
    the backup took a whole round more (docs/performance.md). The pool's bound stops the
    BRPOP while the pool is full.
    """
    global _pool_size, _slots
    _pool_size, _slots = pool_size, slots


def _held(qos: virtual.QoS) -> int:
    """Messages delivered to the consumer and not yet acknowledged (kombu's own count)."""
    return len(qos._delivered or ()) - len(qos._dirty or ())


class PoolBoundQoS(virtual.QoS):
    """kombu's QoS without acknowledgement emulation (dncq's), that consumes only while the
    worker's pool can start what it takes, and tells its connection's poller when a task
    ends."""

    def __init__(self, channel: Any, *args: Any, **kwargs: Any) -> None:
        super().__init__(channel, *args, **kwargs)
        self._task_ended = channel.connection.cycle.task_ended  # the transport's `Poller`

    def can_consume(self) -> bool:
        if _pool_size is not None and _held(self) >= _pool_size:
            return False
        return bool(super().can_consume())

    def ack(self, delivery_tag: Any) -> None:
        super().ack(delivery_tag)
        self._task_ended.set()

    def reject(self, delivery_tag: Any, requeue: bool = False) -> None:
        super().reject(delivery_tag, requeue=requeue)
        self._task_ended.set()

    def restore_unacked(self) -> list[tuple[BaseException, Any]]:
        # The messages taken and not acknowledged go back to the queue at a channel's close;
        # with Redis gone they cannot, and kombu then logged an ERROR and dumped them into a
        # file in /tmp at every restart of Redis. Their targets are in the database, and
        # the reaper queues again what they leave undone (docs/jobs.md, "Recovery").
        failed = super().restore_unacked()
        if failed:
            log.warning("%d messages taken from the broker could not go back to it (%s); "
                        "the reaper queues their targets again", len(failed),
                        type(failed[0][0]).__name__)
        return []


class Channel(redis.Channel):
    """A Redis channel that reuses one client for the commands not made while polling,
    and that can still reach Redis after its connection was closed."""

    _shared_client: Any = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._known_params: dict[bool, dict[str, Any]] = {}
        super().__init__(*args, **kwargs)  # pings Redis: the asynchronous pool's address
        self._connparams(asynchronous=False)  # kept for a pool made after the close
        if self.QoS is virtual.QoS:  # acknowledgement emulation off, as dncq runs it
            self.QoS = PoolBoundQoS  # type: ignore[assignment]  # as kombu assigns its own

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

    def _brpop_read(self, **options: Any) -> bool:
        # kombu 5.7's Channel._brpop_read, then the rest of the same list that the
        # consumer may still take, delivered in the order they were queued.
        try:
            try:
                dest__item = self.client.parse_response(self.client.connection, "BRPOP",
                                                        **options)
            except self.connection_errors:
                self.client.connection.disconnect()  # the next poll reconnects
                raise
            if not dest__item:
                raise Empty()
            key, item = dest__item
            dest = bytes_to_str(key).rsplit(self.sep, 1)[0]
            self._queue_cycle.rotate(dest)
            self.connection._deliver(loads(bytes_to_str(item)), dest)
        finally:
            self._in_poll = None  # type: ignore[assignment]  # as kombu leaves it
            self._flush_brpop_reauth()  # the polling connection is idle: kombu's moment
        self._deliver_more(key, dest)
        return True

    def _deliver_more(self, key: bytes, dest: str) -> None:
        room = self.qos.can_consume_max_estimate()
        count = TAKE_MORE if room is None else min(room, TAKE_MORE)
        # Up to the slots; up to the pool when the poll began with every slot busy (and so
        # after the wait in Poller.get): the BRPOP's message is then one past the slots.
        held = _held(self.qos)
        bound = _pool_size if _slots is None or held > _slots else _slots
        if bound is not None:
            count = min(count, bound - held)
        if count <= 0:
            return
        try:
            with self.conn_or_acquire() as client:
                taken = client.rpop(key, count) or []  # Redis 6.2 and later take a count
        except (redis_errors.ResponseError, *self.connection_errors):
            return  # the one delivered is enough; a broker gone is seen by the next poll
        for i, item in enumerate(taken):
            try:
                self.connection._deliver(loads(bytes_to_str(item)), dest)
            except BaseException:
                rest = taken[i + 1:]
                if rest:  # back at the list's end they were taken from, in their order
                    with self.conn_or_acquire() as client:
                        client.rpush(key, *reversed(rest))
                raise

    @contextlib.contextmanager
    def conn_or_acquire(self, client: Any = None) -> Iterator[Any]:
        if client:
            yield client
            return
        shared = self._shared_client
        if shared is None or shared.connection_pool is not self.pool:  # a new pool after close
            shared = self._shared_client = self._create_client()
        yield shared


class Poller(redis.MultiChannelPoller):
    """kombu's poller of a connection's channels, that waits for a task to end while every
    consuming channel's pool is full.

    kombu stops polling a channel that may take no more, and then sleeps up to a second
    before it looks again: a worker whose pool is full most of the time (a rollout to more
    machines than its slots) would stand idle for most of that second after each task.
    """

    def __init__(self) -> None:
        super().__init__()
        self.task_ended = threading.Event()  # made in the worker: gevent's where patched

    def get(self, callback: Any, timeout: float | None = None) -> Any:
        self.task_ended.clear()  # before the look: an ack after it wakes the wait below
        consuming = [channel for channel in self._channels if channel.active_queues]
        if _pool_size is not None and consuming and \
                not any(channel.qos.can_consume() for channel in consuming):
            self.task_ended.wait(FULL_POOL_WAIT_S if timeout is None
                                 else min(timeout, FULL_POOL_WAIT_S))
            raise Empty()
        if _slots is not None and consuming and \
                all(_held(channel.qos) >= _slots for channel in consuming):
            # What it takes now waits for a slot of its own: the workers with room look
            # first, unless a task of its own ended since its last look (a queue longer
            # than every worker's slots, where waiting would only leave its slots idle).
            self.task_ended.wait(CLAIM_AHEAD_WAIT_S if timeout is None
                                 else min(timeout, CLAIM_AHEAD_WAIT_S))
        return super().get(callback, timeout=timeout)


class Transport(redis.Transport):
    """kombu's Redis transport with `Channel` and `Poller` above."""

    Channel = Channel

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.cycle = Poller()  # type: ignore[assignment]  # kombu's class says None
