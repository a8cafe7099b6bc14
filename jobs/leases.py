"""Per-machine concurrency: database leases that expire when their holder dies.

A machine has `max_concurrent` slots. Each acquisition takes a free or expired slot
under a fresh holder token and renews it while it works. Its group (`job:<id>` for a
job's runner, `api:<uuid>` for a single-machine request) may hold at most one slot
per machine (unique machine+group), so a job's targets on one machine run one after
another even when its task is delivered twice. The leases live in the database, so
the limit holds across every worker, host and API process.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from datetime import timedelta
from typing import Any

from sqlalchemy import bindparam, delete, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from jobs.db import rowcount, session_scope
from jobs.errors import ContractError, ErrorCode
from jobs.models import MachineLease, utcnow

LEASE_TTL_S = 30.0  # a dead holder's slot frees after this long
POLL_S = 0.05  # how often a waiting request looks for a free slot

log = logging.getLogger(__name__)


def take(session: Session, *, machine_id: str, max_concurrent: int, group: str,
         ttl_s: float = LEASE_TTL_S) -> str | None:
    """Take a slot of the machine for `group` in the caller's transaction.

    Returns the holder token, or None when every slot is held (or the group holds one).
    """
    now = utcnow()
    holder = uuid.uuid4().hex
    row = {"machine_id": machine_id, "group": group, "holder": holder,
           "expires_at": now + timedelta(seconds=ttl_s)}
    conn = session.connection()
    insert = _insert_or_nothing(session)
    for clear_expired in (False, True):
        if clear_expired:  # leases of dead holders: clear them so their slots can be taken
            conn.execute(_DELETE_EXPIRED, {"machine_id": machine_id, "now": now})
        for slot in range(max_concurrent):
            if conn.execute(insert, {**row, "slot": slot}).rowcount:
                return holder
    return None


_DELETE_EXPIRED = delete(MachineLease).where(MachineLease.machine_id == bindparam("machine_id"),
                                             MachineLease.expires_at < bindparam("now"))
_DELETE_HOLDER = delete(MachineLease).where(MachineLease.holder == bindparam("holder_token"))


def drop(session: Session, *, holder: str) -> None:
    """Give a slot back in the caller's transaction."""
    session.connection().execute(_DELETE_HOLDER, {"holder_token": holder})


def _insert_or_nothing(session: Session) -> Any:
    """INSERT ... ON CONFLICT DO NOTHING for the database in use (SQLite or PostgreSQL)."""
    return _INSERT_OR_NOTHING[session.get_bind().dialect.name]


_INSERT_OR_NOTHING = {
    "postgresql": postgresql.insert(MachineLease).on_conflict_do_nothing(),
    "sqlite": sqlite.insert(MachineLease).on_conflict_do_nothing(),
}


def acquire(url: str, *, machine_id: str, max_concurrent: int, group: str,
            ttl_s: float = LEASE_TTL_S) -> str | None:
    """`take` in a transaction of its own."""
    with session_scope(url) as session:
        return take(session, machine_id=machine_id, max_concurrent=max_concurrent, group=group,
                    ttl_s=ttl_s)


def renew(url: str, *, holder: str, ttl_s: float = LEASE_TTL_S) -> bool:
    """Push the holder's lease further; False if it was lost (expired and taken)."""
    with session_scope(url) as session:
        return bool(rowcount(session.execute(
            update(MachineLease).where(MachineLease.holder == holder)
            .values(expires_at=utcnow() + timedelta(seconds=ttl_s))
        )))


def release(url: str, *, holder: str) -> None:
    """`drop` in a transaction of its own."""
    with session_scope(url) as session:
        drop(session, holder=holder)


class _Renewer:
    """One thread per process that renews every lease held in it, each every ttl/3."""

    TICK_S = 0.25

    def __init__(self) -> None:
        self._held: dict[str, tuple[str, float, Callable[[], None] | None, float]] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def add(self, url: str, holder: str, ttl_s: float,
            on_renew: Callable[[], None] | None) -> None:
        with self._lock:
            self._held[holder] = (url, ttl_s, on_renew, time.monotonic() + ttl_s / 3)
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="lease-renewer")
                self._thread.start()

    def remove(self, holder: str) -> None:
        with self._lock:
            self._held.pop(holder, None)

    def _run(self) -> None:
        while True:
            time.sleep(self.TICK_S)
            now = time.monotonic()
            with self._lock:
                due = [(h, v) for h, v in self._held.items() if v[3] <= now]
                for holder, (url, ttl_s, on_renew, _) in due:
                    self._held[holder] = (url, ttl_s, on_renew, now + ttl_s / 3)
            for holder, (url, ttl_s, on_renew, _) in due:
                try:
                    renew(url, holder=holder, ttl_s=ttl_s)
                    if on_renew is not None:
                        on_renew()
                except Exception:  # the next tick tries again; the lease outlives one miss
                    log.exception("renewing lease %s failed", holder)


_RENEWER = _Renewer()


class Heartbeat:
    """Keeps a lease alive while the block runs (renewed by the process's renewer thread)."""

    def __init__(self, url: str, *, holder: str, ttl_s: float = LEASE_TTL_S,
                 on_renew: Callable[[], None] | None = None) -> None:
        self.url, self.holder, self.ttl_s, self.on_renew = url, holder, ttl_s, on_renew

    def __enter__(self) -> Heartbeat:
        _RENEWER.add(self.url, self.holder, self.ttl_s, self.on_renew)
        return self

    def __exit__(self, *exc: object) -> None:
        _RENEWER.remove(self.holder)


@contextlib.contextmanager
def hold(url: str, *, machine_id: str, max_concurrent: int, wait_s: float,
         ttl_s: float = LEASE_TTL_S) -> Iterator[None]:
    """Hold a slot for one single-machine request, waiting up to `wait_s` for one.

    Raises:
        ContractError: MACHINE_BUSY when no slot freed in time.
    """
    group = f"api:{uuid.uuid4().hex}"
    deadline = time.monotonic() + wait_s
    while not (holder := acquire(url, machine_id=machine_id, max_concurrent=max_concurrent,
                                 group=group, ttl_s=ttl_s)):
        if time.monotonic() >= deadline:
            raise ContractError(ErrorCode.MACHINE_BUSY,
                                f"machine {machine_id} stayed busy for {wait_s:g} s")
        time.sleep(POLL_S)
    try:
        with Heartbeat(url, holder=holder, ttl_s=ttl_s):
            yield
    finally:
        release(url, holder=holder)
