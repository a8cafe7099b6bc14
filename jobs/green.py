"""A worker on a gevent pool: the patching at start, and calls kept off its one thread.

`dncq worker --pool gevent` runs every task as a greenlet on one OS thread. The standard
library must be patched before anything else imports it (what Celery's own `celery`
command does first thing), and work that would spread over the cores from native threads
(zlib-ng's deflate drops the interpreter lock) goes to gevent's pool of native threads,
the greenlet waiting for it without blocking the others.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
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


def run_native(fn: Callable[..., T], *args: Any) -> T:
    """`fn(*args)`, on a native thread when the process runs on gevent, else in place."""
    if not active():
        return fn(*args)
    from gevent import get_hub

    return get_hub().threadpool.apply(fn, args)  # type: ignore[no-any-return]
