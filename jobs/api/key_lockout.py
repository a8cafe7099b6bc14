"""Wrong API keys at the edge: each one counted for the client's address, and every keyed
request from an address locked out for them refused (429), the right key too.

The right key is refused as well, or the lock-out would still answer whether a guess was
right. A right key resets nothing: only the window's end forgets wrong keys, so that right
keys sent between wrong ones win a guesser no more guesses. The addresses this process
found locked, and those locked as it started, are kept in memory until their lock-out ends:
a flood of keys from one costs the database one read in RECHECK_S.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from datetime import datetime
from typing import NoReturn

from fastapi import FastAPI, Request
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session

from jobs.api.errors import AuthError, KeysLockedOut
from jobs.auth import audit, lockouts, wrong_keys
from jobs.auth.lockouts import Lockout
from jobs.db import session_scope
from jobs.errors import ErrorCode
from jobs.models import utcnow
from jobs.settings import Settings

log = logging.getLogger(__name__)

# The most addresses kept in memory; past it the ones whose lock-out ended are forgotten,
# then the soonest to end (a forgotten one is read from the database again).
MAX_KEPT_ADDRESSES = 10_000
RECHECK_S = lockouts.RECHECK_S
WRONG_KEY = "the key sent is neither this dncq's admin key nor one of its named keys"


class LockedAddresses:
    """The addresses this process found locked out, each until when, and when the database
    last said so."""

    def __init__(self, recheck_s: float = RECHECK_S) -> None:
        self.recheck_s = recheck_s
        self._until: dict[str, tuple[datetime, float]] = {}  # until, read at (monotonic s)
        self._lock = threading.Lock()  # routes run on the thread pool

    def until(self, address: str) -> datetime | None:
        """Until when `address` is locked, as this process knows; None: not known locked."""
        kept = self._until.get(address)
        if kept is not None and kept[0] <= utcnow():
            self.forget(address)
            return None
        return kept[0] if kept is not None else None

    def recheck_due(self, address: str) -> bool:
        """Whether the database is to be asked again about `address` (once in `recheck_s`,
        by the one request that gets True)."""
        with self._lock:
            kept = self._until.get(address)
            now_s = time.monotonic()
            if kept is None or now_s - kept[1] < self.recheck_s:
                return False
            self._until[address] = (kept[0], now_s)
            return True

    def add(self, address: str, until: datetime) -> None:
        """Keep `address` as locked until `until`, as the database says now."""
        with self._lock:
            if len(self._until) >= MAX_KEPT_ADDRESSES:
                now = utcnow()
                self._until = {a: k for a, k in self._until.items() if k[0] > now}
                if len(self._until) >= MAX_KEPT_ADDRESSES:
                    del self._until[min(self._until, key=lambda a: self._until[a][0])]
            self._until[address] = (until, time.monotonic())

    def forget(self, address: str) -> None:
        """Take `address` again: its lock-out ended."""
        with self._lock:
            self._until.pop(address, None)


def remember_locked(app: FastAPI) -> None:
    """Keep in `app`'s memory the addresses locked out as it starts: the admin key is
    compared without asking the database, and a restarted process took it from a locked
    address until that address's next wrong key found the lock-out.

    A database not reachable yet (started after the API) leaves the process as it was: it
    serves, and a locked address's next wrong key finds its lock-out there.
    """
    settings: Settings = app.state.settings
    try:
        with session_scope(settings.resolved_database_url) as session:
            locked = wrong_keys.locked_now(session=session, most=MAX_KEPT_ADDRESSES)
    except SQLAlchemyError as exc:
        log.warning("could not read the addresses locked out for wrong API keys as the API "
                    "started (%s): each is refused again at its next wrong key",
                    type(exc).__name__)
        return
    for address, until in locked.items():
        app.state.locked_addresses.add(address, until)


def end_lockout(request: Request, *, session: Session, address: str) -> list[Lockout]:
    """End the lock-outs of the address `address` names, in the database (the caller
    commits) and in this process at once; other processes take it within RECHECK_S."""
    return lockouts.end_kept(session=session, address=address, kept=_locked(request))


def client_address(request: Request) -> str:
    """The address a request came from (uvicorn's, from X-Forwarded-For for a trusted proxy)."""
    return wrong_keys.counted_address(request.client.host if request.client else None)


def _locked(request: Request) -> LockedAddresses:
    return request.app.state.locked_addresses  # type: ignore[no-any-return]


def _refused(request: Request, address: str, until: datetime, *, read: bool = True) -> NoReturn:
    """429 for `address`, locked until `until`; `read`: as the database said just now, kept
    in memory with the time of that read (a refusal from memory alone keeps the time, or an
    address sending keys more often than RECHECK_S would never be asked about again)."""
    if read:
        _locked(request).add(address, until)
    # The lock-out's one entry in the audit trail stands for every request it refuses: a
    # flood of them would otherwise write a row each.
    request.state.audit_skip = True
    retry_after_s = max(1, math.ceil((until - utcnow()).total_seconds()))
    raise KeysLockedOut(f"too many wrong API keys came from {address}: every key from it is "
                        f"refused for {retry_after_s} s more (until "
                        f"{until:%Y-%m-%d %H:%M:%S} UTC)", retry_after_s=retry_after_s)


def refuse_known_locked(request: Request) -> None:
    """429 when this process knows the request's address is locked out; asks the database
    only once in RECHECK_S whether the lock-out was ended elsewhere."""
    address = client_address(request)
    locked = _locked(request)
    until = locked.until(address)
    if until is None:
        return
    rechecked = locked.recheck_due(address)
    if rechecked:  # ended through another process since?
        settings: Settings = request.app.state.settings
        with session_scope(settings.resolved_database_url) as session:
            until = wrong_keys.locked_until(session=session, address=address)
        if until is None:
            locked.forget(address)
            return
    _refused(request, address, until, read=rechecked)


def refuse_locked(request: Request, *, session: Session) -> None:
    """429 when the database says the request's address is locked out (by this process or
    another); a read, no write."""
    address = client_address(request)
    until = wrong_keys.locked_until(session=session, address=address)
    if until is not None:
        _refused(request, address, until)


def refuse_wrong_key(request: Request, *, session: Session, settings: Settings) -> NoReturn:
    """403 for a key nobody has, counted for the request's address and committed; 429 when
    it is one too many (written once to the audit trail as the address's lock-out)."""
    address = client_address(request)
    counted = wrong_keys.count_wrong_key(session=session, settings=settings, address=address)
    if counted.locked_now:
        assert counted.locked_until is not None
        audit.record(session=session, principal=None,
                     address=request.client.host if request.client else None,
                     method=request.method,
                     path=request.url.path, status=429, action="lock out", target=address,
                     detail={"failures": settings.signin_max_failures,
                             "until": counted.locked_until.isoformat()})
    session.commit()  # the caller's rollback, as it raises, keeps the count
    if counted.locked_until is not None:
        _refused(request, address, counted.locked_until)
    raise AuthError(403, ErrorCode.AUTH_INVALID, WRONG_KEY)  # else HTTP's bare "Forbidden"
