"""psycopg's wait for a query's socket, made for a gevent worker.

psycopg waits on its connection's socket in one place, `psycopg.waiting.wait`. Under
gevent it picks its `poll()` variant, which gevent emulates with a result object and a
watcher made and started anew at every call: 9 % of a gevent worker's interpreter time in a
mass rollout (bench/batch_send.py at latency 0, py-spy). Waiting on an io watcher of the
hub directly is what gevent's own sockets do, a fraction of that.
"""

from __future__ import annotations

import select
from time import monotonic
from typing import Any

from psycopg import errors, waiting
from psycopg.abc import RV, PQGen

_POLL_MASKS = {waiting.WAIT_R: select.POLLIN, waiting.WAIT_W: select.POLLOUT,
               waiting.WAIT_RW: select.POLLIN | select.POLLOUT}


def install() -> None:
    """Make psycopg wait through gevent's hub; for a process that runs on gevent."""
    waiting.wait = wait_green  # type: ignore[assignment]


def wait_green(gen: PQGen[RV], fileno: int, interval: float = 0.0,
               timeout: float | None = None) -> RV:
    """`psycopg.waiting.wait`, on gevent: the greenlet sleeps until the socket is ready.

    `interval` is psycopg's pause to look for Ctrl-C, which the hub sees anyway; `timeout`
    ends the wait with psycopg's own error, as its functions do.
    """
    from gevent import Timeout, get_hub

    hub = get_hub()
    deadline = None if timeout is None else monotonic() + timeout
    try:
        wanted = next(gen)
        while True:
            watcher = hub.loop.io(fileno, int(wanted))  # libev: 1 read, 2 write, as Wait
            if deadline is None:
                hub.wait(watcher)
            else:
                try:
                    with Timeout(max(0.0, deadline - monotonic()), _Expired):
                        hub.wait(watcher)
                except _Expired:
                    raise errors._WaitTimeout("wait timeout expired") from None
            wanted = gen.send(_ready(fileno, wanted))
    except StopIteration as done:
        result: RV = done.value
        return result


class _Expired(Exception):
    """The wait's own timeout, told apart from any other the greenlet may get."""


def _ready(fileno: int, wanted: Any) -> Any:
    """What the socket is ready for: what was waited for, unless that was either."""
    if wanted != waiting.WAIT_RW:
        return waiting.READY_R if wanted == waiting.WAIT_R else waiting.READY_W
    poll = _unpatched_poll()
    poll.register(fileno, _POLL_MASKS[wanted])
    events = poll.poll(0)
    ready = 0
    for _, event in events:
        if event & select.POLLIN:
            ready |= waiting.READY_R
        if event & (select.POLLOUT | select.POLLERR | select.POLLHUP):
            ready |= waiting.READY_W
    return ready or waiting.READY_RW  # woken for something: let libpq find out what


def _unpatched_poll() -> Any:
    from gevent.monkey import get_original

    return get_original("select", "poll")()
