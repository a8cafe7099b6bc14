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
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from operator import itemgetter

from sqlalchemy import Connection, Integer, String, bindparam, delete, func, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from jobs.db import session_scope
from jobs.errors import ContractError, ErrorCode
from jobs.models import MachineLease, UTCDateTime, utcnow
from jobs.settings import Settings

LEASE_TTL_S: float = Settings.model_fields["lease_ttl_s"].default  # the setting's default
# A holder pushes each of its leases to HOLD_SHARE of a TTL ahead every RENEW_SHARE of one.
# A live holder may then miss renewals for 2/3 of a TTL before it loses a lease (a stalled
# database, a busy process), as when leases were pushed a whole TTL ahead every third of
# one; a dead holder's leases run out within 5/6 of a TTL instead of a whole one, so that
# with the reaper's next pass and the next worker's start its targets run again within
# one TTL of its death.
RENEW_SHARE = 1 / 6
HOLD_SHARE = 5 / 6
POLL_S = 0.05  # how often a waiting request looks for a free slot
ASK_AGAIN_S = 0.5  # how often a waiting request asks a listener again to give the machine up

log = logging.getLogger(__name__)


def held_until(now: datetime, ttl_s: float) -> datetime:
    """Until when a lease taken or renewed at `now` holds."""
    return now + timedelta(seconds=ttl_s * HOLD_SHARE)


def take(session: Session, *, machine_id: str, max_concurrent: int, group: str,
         ttl_s: float = LEASE_TTL_S) -> str | None:
    """Take a slot of the machine for `group` in the caller's transaction.

    Returns the holder token, or None when every slot is held (or the group holds one).
    """
    return take_many(session, [Want(machine_id, max_concurrent, group)], ttl_s=ttl_s)[0]


@dataclass(frozen=True)
class Want:
    """A slot wanted: of which machine, its limit, for which group."""

    machine_id: str
    max_concurrent: int
    group: str


def take_many(session: Session, wants: Sequence[Want],
              ttl_s: float = LEASE_TTL_S) -> list[str | None]:
    """`take` for many machines at once: a holder token or None per want, in order.

    Slot by slot, one multi-row insert that skips taken slots; then once more after
    clearing the expired leases of the machines still without one.
    """
    now = utcnow()
    expires_at = held_until(now, ttl_s)
    rows = [{"machine_id": w.machine_id, "group": w.group, "holder": uuid.uuid4().hex}
            for w in wants]
    got: set[str] = set()
    conn = session.connection()
    insert = _INSERTERS[session.get_bind().dialect.name]
    for clear_expired in (False, True):
        left = [i for i, row in enumerate(rows) if row["holder"] not in got]
        if not left:
            break
        if clear_expired:  # leases of dead holders: clear them so their slots can be taken
            conn.execute(_DELETE_EXPIRED, {"machines": sorted({wants[i].machine_id
                                                               for i in left}), "now": now})
        for slot in range(max(wants[i].max_concurrent for i in left)):
            # In one global order, not the request's: two workers inserting the same
            # machines in opposite orders would each wait for the other's rows (deadlock).
            trying = sorted((rows[i] for i in left
                             if wants[i].max_concurrent > slot and rows[i]["holder"] not in got),
                            key=_LOCK_ORDER)
            if trying:
                got.update(insert(conn, trying, slot, expires_at))
    return [row["holder"] if row["holder"] in got else None for row in rows]


_LOCK_ORDER = itemgetter("machine_id", "group")
_DELETE_EXPIRED = delete(MachineLease).where(
    MachineLease.machine_id.in_(bindparam("machines", expanding=True)),
    MachineLease.expires_at < bindparam("now"))
_DELETE_HOLDERS = delete(MachineLease).where(
    MachineLease.holder.in_(bindparam("holders", expanding=True)))
def _insert_rows(conn: Connection, rows: list[dict[str, str]], slot: int,
                 expires_at: datetime) -> Sequence[str]:
    """INSERT ... ON CONFLICT DO NOTHING of one slot for each row; the holders inserted."""
    return conn.execute(_INSERT_ROWS, [{**row, "slot": slot, "expires_at": expires_at}
                                       for row in rows]).scalars().all()


_INSERT_ROWS = sqlite.insert(MachineLease).on_conflict_do_nothing().returning(MachineLease.holder)


def _insert_arrays(conn: Connection, rows: list[dict[str, str]], slot: int,
                   expires_at: datetime) -> Sequence[str]:
    """`_insert_rows` for PostgreSQL: the rows as three arrays, so the statement's text
    never changes. A multi-row VALUES is new text for every batch size, and psycopg
    re-parses such text each time: that was most of a runner's lease cost."""
    return conn.execute(_INSERT_ARRAYS, {
        "machine_ids": [row["machine_id"] for row in rows],
        "groups": [row["group"] for row in rows],
        "holders": [row["holder"] for row in rows],
        "slot": slot, "expires_at": expires_at}).scalars().all()


_ROWS = func.unnest(bindparam("machine_ids", type_=postgresql.ARRAY(String)),
                    bindparam("groups", type_=postgresql.ARRAY(String)),
                    bindparam("holders", type_=postgresql.ARRAY(String))
                    ).table_valued("machine_id", "group", "holder").render_derived()
_INSERT_ARRAYS = postgresql.insert(MachineLease).from_select(
    ["machine_id", "group", "holder", "slot", "expires_at"],
    select(_ROWS.c.machine_id, _ROWS.c.group, _ROWS.c.holder,
           bindparam("slot", type_=Integer), bindparam("expires_at", type_=UTCDateTime())),
).on_conflict_do_nothing().returning(MachineLease.holder)
_INSERTERS: dict[str, Callable[[Connection, list[dict[str, str]], int, datetime],
                               Sequence[str]]] = {
    "postgresql": _insert_arrays, "sqlite": _insert_rows}


def kept(session: Session, holders: Sequence[str], *, ttl_s: float = LEASE_TTL_S) -> set[str]:
    """Those of `holders` whose slot is still theirs, pushed ahead as a renewal does, in the
    caller's transaction.

    A holder whose process stalled longer than its lease (stopped, swapped out, starved of
    CPU) may have lost the slot meanwhile: its lease expired, was cleared, and the slot was
    taken by another. Its row is gone then, and so is the holder's right to the machine.
    """
    if not holders:
        return set()
    rows = session.connection().execute(
        update(MachineLease).where(MachineLease.holder.in_(holders))
        .values(expires_at=held_until(utcnow(), ttl_s)).returning(MachineLease.holder))
    return set(rows.scalars())


def drop(session: Session, *, holder: str) -> None:
    """Give a slot back in the caller's transaction."""
    drop_many(session, [holder])


def drop_many(session: Session, holders: Sequence[str]) -> None:
    """Give slots back in the caller's transaction."""
    if holders:
        session.connection().execute(_DELETE_HOLDERS, {"holders": list(holders)})


def acquire(url: str, *, machine_id: str, max_concurrent: int, group: str,
            ttl_s: float = LEASE_TTL_S) -> str | None:
    """`take` in a transaction of its own."""
    with session_scope(url) as session:
        return take(session, machine_id=machine_id, max_concurrent=max_concurrent, group=group,
                    ttl_s=ttl_s)


def renew(url: str, *, holder: str, ttl_s: float = LEASE_TTL_S) -> bool:
    """Push the holder's lease further; False if it was lost (expired and taken)."""
    return renew_many(url, [holder], ttl_s=ttl_s) == 1


def renew_many(url: str, holders: Sequence[str], *, ttl_s: float = LEASE_TTL_S) -> int:
    """Push the holders' leases further, in one statement; how many were still held."""
    with session_scope(url) as session:
        return len(kept(session, holders, ttl_s=ttl_s))


def release(url: str, *, holder: str) -> None:
    """`drop` in a transaction of its own."""
    with session_scope(url) as session:
        drop(session, holder=holder)


LISTEN_GROUP = "listen:"  # a listener's lease: it waits on the machine's link for its operator
YIELD_GROUP = "yield:"  # a listener's lease that others wait for: it gives the machine up


def listen_group(machine_id: str) -> str:
    """The group of the machine's listener (one per machine, across every worker)."""
    return f"{LISTEN_GROUP}{machine_id}"


def ask_listener_to_yield(url: str, *, machine_id: str) -> None:
    """Tell the machine's listener, if one holds it, that a request waits for the machine."""
    with session_scope(url) as session:
        session.execute(update(MachineLease).where(
            MachineLease.machine_id == machine_id,
            MachineLease.group == listen_group(machine_id))
            .values(group=f"{YIELD_GROUP}{machine_id}"))


def asked_to_yield(url: str, *, holder: str) -> bool:
    """Whether the listener holding `holder` should give the machine up (or has lost it)."""
    with session_scope(url) as session:
        group = session.scalar(select(MachineLease.group).where(MachineLease.holder == holder))
    return group is None or group.startswith(YIELD_GROUP)


class _Renewer:
    """One thread per process that renews every lease held in it, each every RENEW_SHARE
    of its TTL: those due together in one statement per database."""

    TICK_S = 0.25

    def __init__(self) -> None:
        self._held: dict[str, tuple[str, float, Callable[[], None] | None, float]] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def add(self, url: str, holder: str, ttl_s: float,
            on_renew: Callable[[], None] | None) -> None:
        with self._lock:
            self._held[holder] = (url, ttl_s, on_renew, time.monotonic() + ttl_s * RENEW_SHARE)
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
                    self._held[holder] = (url, ttl_s, on_renew, now + ttl_s * RENEW_SHARE)
            together: dict[tuple[str, float], list[str]] = {}
            for holder, (url, ttl_s, _, _) in due:
                together.setdefault((url, ttl_s), []).append(holder)
            renewed: set[str] = set()
            for (url, ttl_s), holders in together.items():
                try:
                    still_held = renew_many(url, holders, ttl_s=ttl_s)
                except Exception:  # the next round tries again; a lease outlives three misses
                    log.exception("renewing %d leases failed", len(holders))
                else:
                    renewed.update(holders)
                    if still_held < len(holders):
                        # Expired before this round renewed it, and cleared by a taker: the
                        # machine may have two operations at once until this holder ends.
                        log.warning("%d machine leases of this process expired before they "
                                    "were renewed (lease_ttl_s %g s): the host or the database "
                                    "was too slow; another holder may use those machines now",
                                    len(holders) - still_held, ttl_s)
            # What a lease covers (a job's targets) is kept alive only when the lease was.
            for holder, (_, _, on_renew, _) in due:
                if on_renew is None or holder not in renewed:
                    continue
                try:
                    on_renew()
                except Exception:
                    log.exception("renewing what lease %s holds failed", holder)


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
    asked_at: float | None = None
    while not (holder := acquire(url, machine_id=machine_id, max_concurrent=max_concurrent,
                                 group=group, ttl_s=ttl_s)):
        # Asked again while waiting: a listener that gave the machine up may have taken it
        # back on its next tick before this request's next look.
        if asked_at is None or time.monotonic() - asked_at >= ASK_AGAIN_S:
            ask_listener_to_yield(url, machine_id=machine_id)
            asked_at = time.monotonic()
        if time.monotonic() >= deadline:
            raise ContractError(ErrorCode.MACHINE_BUSY,
                                f"machine {machine_id} stayed busy for {wait_s:g} s")
        time.sleep(POLL_S)
    try:
        with Heartbeat(url, holder=holder, ttl_s=ttl_s):
            yield
    finally:
        release(url, holder=holder)
