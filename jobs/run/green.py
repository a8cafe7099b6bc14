"""A worker on a gevent pool: the patching at start, and calls kept off its one thread.

`dncq worker --pool gevent` runs every task as a greenlet on one OS thread. The standard
library must be patched before anything else imports it (what Celery's own `celery`
command does first thing), and work that would spread over the cores from native threads
(a backup's deflate drops the interpreter lock) goes to native threads, one per core,
the greenlet waiting for it without blocking the others.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from typing import Any, TypeVar

T = TypeVar("T")


def patch(argv: list[str]) -> None:
    """Patch the standard library when `argv` asks Celery for a gevent pool."""
    from celery import maybe_patch_concurrency

    maybe_patch_concurrency(argv)
    if active():
        # httpcore imports trio when it is installed, and trio's import fails once gevent
        # has taken select.epoll away; a green worker runs no trio code.
        sys.modules.setdefault("trio", None)  # type: ignore[arg-type]


def active() -> bool:
    """Whether this process runs on gevent (its threads are greenlets)."""
    monkey = sys.modules.get("gevent.monkey")
    return monkey is not None and bool(monkey.is_module_patched("threading"))


def run_on_a_core(fn: Callable[..., T], *args: Any) -> T:
    """`fn(*args)`, at most one such call per core at once; for work that drops the GIL.

    More threads running such work at once than there are cores only queue for the
    interpreter lock in between (backup bench run 1, 50 machines deflating at once: 6.1 s
    without a limit, 4.5 s with one). On gevent the calls go to a pool of native threads
    of their own, one per core; a greenlet waits for its call's result without holding
    up the others. That was faster than a semaphore in front of gevent's shared pool
    (run 1: 1.13 and 1.29 s against 1.36 and 1.66 s, alternating). Otherwise the call
    runs in place, under a semaphore.
    """
    if active():
        return _core_threads().apply(fn, args)  # type: ignore[no-any-return]
    with _CORE_SLOTS:
        return fn(*args)


def start_on_a_core(fn: Callable[..., T], *args: Any) -> Callable[[], T]:
    """`run_on_a_core(fn, *args)` started now; returns the wait for its result.

    The caller goes on meanwhile (a backup reads the machine's next file while the last
    one deflates), and waits when it needs the result.
    """
    if active():
        return _core_threads().spawn(fn, *args).get  # type: ignore[no-any-return]
    return _core_executor().submit(run_on_a_core, fn, *args).result


CORES = os.cpu_count() or 1
_CORE_SLOTS = threading.BoundedSemaphore(CORES)


@cache
def _core_executor() -> ThreadPoolExecutor:
    """Threads that wait for a core slot for callers that do not wait themselves."""
    return ThreadPoolExecutor(CORES, thread_name_prefix="dncq-core")


@cache
def _core_threads() -> Any:
    """gevent's pool of native threads, made in the hub's thread on first use."""
    from gevent.threadpool import ThreadPool

    return ThreadPool(CORES)
