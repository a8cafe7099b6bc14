"""Calls that drop the interpreter lock, kept off a gevent worker's one thread.

In a worker started with `--pool gevent` every task shares one OS thread, so work that
spreads over the cores from native threads (zlib-ng's deflate drops the lock) would run
on a single core there. Such calls go to gevent's pool of native threads instead, and the
greenlet waits for them without blocking the others. Anywhere else they run in place.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


def run(fn: Callable[..., T], *args: Any) -> T:
    """`fn(*args)`, on a native thread when the process runs on gevent."""
    if not _green():
        return fn(*args)
    from gevent import get_hub

    return get_hub().threadpool.apply(fn, args)  # type: ignore[no-any-return]


def _green() -> bool:
    monkey = sys.modules.get("gevent.monkey")
    return monkey is not None and bool(monkey.is_module_patched("threading"))
