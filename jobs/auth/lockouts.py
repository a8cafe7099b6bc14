"""The client addresses an administrator may release, listed and ended together: those
counted for wrong API keys (jobs.auth.wrong_keys) and those counted for failed dashboard
sign-ins with the admin key (the `admin from <address>` rows of jobs.auth.service).

Both lock out an address, not a user: a script sending an old key from the host where the
administrator works keeps that host out of the API, and five wrong guesses at the admin key
keep its browser out of the dashboard. Ending an address ends both, so that the
administrator has one thing to ask for.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Protocol

from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs import db
from jobs.auth.models import SignInCount, WrongKeyCount
from jobs.auth.wrong_keys import row_named
from jobs.errors import ContractError, ErrorCode
from jobs.models import utcnow
from jobs.settings import Settings

API_KEYS = "api keys"  # what an address's count is of
ADMIN_SIGNINS = "admin sign-ins"
_FROM = " from "  # a key sign-in's row: "admin from 10.0.0.7"
# How often an API process asks the database again, for an address it keeps as locked out
# (jobs.api.key_lockout), whether an administrator ended the lock-out through another
# process: one read in this many seconds for all of that address's requests.
RECHECK_S = 10


@dataclass(frozen=True)
class Lockout:
    """One count of an address: of what, its failures in the current window (while it is
    locked out, those that locked it out), since when, and until when the address is
    locked out for it (None: it is not)."""

    address: str
    counted: str
    failures: int
    failed_since: datetime | None
    locked_until: datetime | None


def counted_now(*, session: Session, settings: Settings) -> list[Lockout]:
    """The counts locked out now or with failures in the current window: locked first, then
    by address, an address's wrong keys before its sign-ins."""
    now = utcnow()
    window_start = now - timedelta(seconds=settings.signin_window_s)
    keys = session.scalars(select(WrongKeyCount).where(
        (WrongKeyCount.locked_until > now)
        | ((WrongKeyCount.failures > 0) & (WrongKeyCount.failed_since >= window_start))))
    signins = session.scalars(select(SignInCount).where(
        SignInCount.name.contains(_FROM, autoescape=True),
        (SignInCount.locked_until > now)
        | ((SignInCount.failed_signins > 0) & (SignInCount.failed_since >= window_start))))
    found = [*(_of(r.address, API_KEYS, r.failures, r.failed_since, r.locked_until, now,
                   window_start) for r in keys),
             *(_of(r.name.partition(_FROM)[2], ADMIN_SIGNINS, r.failed_signins,
                   r.failed_since, r.locked_until, now, window_start) for r in signins)]
    return sorted(found, key=lambda c: (c.locked_until is None, c.address,
                                        c.counted != API_KEYS))


def end(*, session: Session, address: str) -> list[Lockout]:
    """Forget every count of `address` (an IPv6 address's: its /64's) and so end its
    lock-outs; the counts as they were, wrong keys first (PATH_NOT_FOUND when none is
    kept). The caller commits."""
    row = row_named(address)
    now = utcnow()
    keys = session.scalar(db.held(session, select(WrongKeyCount).where(
        WrongKeyCount.address == row)))
    signins = list(session.scalars(db.held(session, select(SignInCount).where(
        SignInCount.name.endswith(_FROM + row, autoescape=True)))))
    if keys is None and not signins:
        raise ContractError(ErrorCode.PATH_NOT_FOUND,
                            f"no wrong API keys nor failed sign-ins are counted for {address}")
    ended = []
    if keys is not None:
        ended.append(_of(row, API_KEYS, keys.failures, keys.failed_since, keys.locked_until,
                         now, None))
        session.delete(keys)
    for signin in signins:
        ended.append(_of(row, ADMIN_SIGNINS, signin.failed_signins, signin.failed_since,
                         signin.locked_until, now, None))
        session.delete(signin)
    session.flush()
    return ended


def ended_detail(ended: list[Lockout]) -> dict[str, dict[str, str | None]]:
    """What an end of lock-outs writes to the audit trail: each count ended, and until when
    it had locked the address (None: it had not)."""
    return {"ended": {c.counted: c.locked_until.isoformat() if c.locked_until else None
                      for c in ended}}


class KeptLocked(Protocol):
    """The addresses an API process keeps in memory as locked out (jobs.api.key_lockout)."""

    def forget(self, address: str) -> None:
        """Take `address` again: its lock-out ended."""


def end_kept(*, session: Session, address: str, kept: KeptLocked) -> list[Lockout]:
    """`end`, and forget the address in `kept` at once, so that the process keeping it
    takes its keys again now rather than at its next look at the database."""
    ended = end(session=session, address=address)
    kept.forget(ended[0].address)
    return ended


def _of(address: str, counted: str, failures: int, failed_since: datetime | None,
        locked_until: datetime | None, now: datetime,
        window_start: datetime | None) -> Lockout:
    """A count as it stands at `now`: a lock-out that ended is shown as none, and failures
    outside the window (None: not asked) too, but those that locked it out while it lasts."""
    locked = locked_until is not None and locked_until > now
    shown = failed_since is not None and (
        locked or window_start is None or failed_since >= window_start)
    return Lockout(address, counted, failures if shown else 0,
                   failed_since if shown else None, locked_until if locked else None)
