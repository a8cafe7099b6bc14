"""Group commit: the database work of many runner threads, done in shared transactions.

A worker runs dozens of machines at once, and each of them begins and finishes targets
a few milliseconds of database work at a time. Done thread by thread, that is a
transaction per step and a dozen statements per target, and on a small host the
threads spend more time handing the interpreter lock around than working. Instead a
runner hands its request to one thread per process, which takes every request that
arrived meanwhile and serves them together: set-based statements, one commit. A
request waits for at most the batch before it; nothing is delayed on purpose.

When a shared transaction fails (a deadlock with another worker, a lost connection),
each of its requests is tried again alone, so one bad request fails only its caller.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Generic, TypeVar

from sqlalchemy.orm import Session

from jobs.db import session_scope

Request = TypeVar("Request")
Result = TypeVar("Result")

MAX_BATCH = 256  # requests per transaction; more wait for the next one

log = logging.getLogger(__name__)


class GroupCommit(Generic[Request, Result]):
    """Serves `call(url, request)` from many threads through `serve(session, requests)`.

    `serve` gets the requests of one database in arrival order and returns one result
    per request, in the same order, inside the transaction that commits them.
    """

    def __init__(self, name: str,
                 serve: Callable[[Session, Sequence[Request]], Sequence[Result]]) -> None:
        self.name = name
        self._serve = serve
        self._reset()
        os.register_at_fork(after_in_child=self._reset)  # a forked child starts afresh

    def _reset(self) -> None:
        self._queue: queue.SimpleQueue[tuple[str, Request, Future[Result]]] = \
            queue.SimpleQueue()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._served = threading.Condition()
        self._outstanding = 0  # requests submitted and not yet served

    def call(self, url: str, request: Request) -> Result:
        """Serve one request with whatever else is waiting; raises what serving it raised."""
        return self.submit(url, request).result()

    def submit(self, url: str, request: Request) -> Future[Result]:
        """Queue one request and go on; its future gets the result once it is committed."""
        future: Future[Result] = Future()
        with self._served:
            self._outstanding += 1
        self._queue.put((url, request, future))
        self._ensure_thread()
        return future

    def drain(self, timeout_s: float) -> bool:
        """Wait until every request submitted so far is served; False if time ran out."""
        with self._served:
            return self._served.wait_for(lambda: self._outstanding == 0, timeout_s)

    def _ensure_thread(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            return
        with self._lock:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
                self._thread.start()

    def _run(self) -> None:
        while True:
            batch = [self._queue.get()]
            while len(batch) < MAX_BATCH:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            by_url: dict[str, list[tuple[Request, Future[Result]]]] = {}
            for url, request, future in batch:
                by_url.setdefault(url, []).append((request, future))
            for url, items in by_url.items():
                self._commit(url, items)
            with self._served:
                self._outstanding -= len(batch)
                self._served.notify_all()

    def _commit(self, url: str, items: list[tuple[Request, Future[Result]]]) -> None:
        try:
            with session_scope(url) as session:
                results = self._serve(session, [request for request, _ in items])
        except BaseException as exc:
            if len(items) == 1:
                items[0][1].set_exception(exc)
                return
            log.info("%s: a transaction of %d requests failed (%s); serving them one by one",
                     self.name, len(items), type(exc).__name__)
            for item in items:
                self._commit(url, [item])
            return
        for (_, future), result in zip(items, results, strict=True):
            future.set_result(result)

