"""Wrong API keys counted per client address, and the addresses locked out for them.

`DNCQ_SIGNIN_MAX_FAILURES` wrong keys from one address within `DNCQ_SIGNIN_WINDOW_S` lock
it out for `DNCQ_SIGNIN_LOCKOUT_S`, as failed sign-ins lock out a name. The count is in the
database, so that it holds across every API process that shares it.
"""

from __future__ import annotations

import hashlib
import ipaddress
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs.auth.guessers import IPV6_PREFIX, guesser_of, held_count
from jobs.auth.models import WRONG_KEY_ADDRESS_CHARS, WrongKeyCount
from jobs.models import utcnow
from jobs.settings import Settings

# Where the client's address is not known (a Unix socket): such clients share one count.
UNKNOWN_ADDRESS = "unknown"


@dataclass(frozen=True)
class Counted:
    """What one wrong key left: the lock-out the address is under now (None: none), and
    whether this key is the one that began it (the audit trail's)."""

    locked_until: datetime | None
    locked_now: bool = False


def counted_address(address: str | None) -> str:
    """The row an address's wrong keys are counted in (an IPv6 address's: its /64's)."""
    address = guesser_of(address) if address else UNKNOWN_ADDRESS
    # An address longer than the column (no IP address is) shares a row by its digest.
    return address if len(address) <= WRONG_KEY_ADDRESS_CHARS else \
        f"#{hashlib.sha256(address.encode()).hexdigest()[:32]}"


def locked_until(*, session: Session, address: str | None) -> datetime | None:
    """Until when `address` is locked out (None: it is not), read without a write."""
    until = session.scalar(select(WrongKeyCount.locked_until).where(
        WrongKeyCount.address == counted_address(address)))
    return until if until is not None and until > utcnow() else None


def row_named(address: str) -> str:
    """The row an administrator's `address` names: a client address (an IPv6 one stands for
    its /64), or a row's own name as listed (`2001:db8:7:1::/64`, in any spelling)."""
    if "/" in address:
        try:
            network = ipaddress.ip_network(address.strip(), strict=False)
        except ValueError:
            return address
        whole_host = network.prefixlen >= (IPV6_PREFIX if network.version == 6 else 32)
        # A wider network holds many rows: it names none.
        return counted_address(str(network.network_address)) if whole_host else address
    return counted_address(address.strip())


def locked_now(*, session: Session, most: int) -> dict[str, datetime]:
    """The addresses locked out now, each until when: the `most` whose lock-outs end last."""
    rows = session.execute(
        select(WrongKeyCount.address, WrongKeyCount.locked_until)
        .where(WrongKeyCount.locked_until > utcnow())
        .order_by(WrongKeyCount.locked_until.desc()).limit(most))
    return {address: until for address, until in rows if until is not None}


def count_wrong_key(*, session: Session, settings: Settings, address: str | None) -> Counted:
    """Count one wrong key from `address`, and lock it out when it is one too many.

    The row is made if it is not there and held as other wrong keys left it: two sent at the
    same moment, to this process or another, each count. The caller commits.
    """
    counted: WrongKeyCount = held_count(session, WrongKeyCount.address,
                                        counted_address(address),
                                        window_s=settings.signin_window_s, failures=0)
    now = utcnow()
    if counted.locked_until is not None and counted.locked_until > now:
        return Counted(counted.locked_until)  # locked by another key meanwhile
    if counted.locked_until is not None or counted.failed_since is None or \
            now - counted.failed_since > timedelta(seconds=settings.signin_window_s):
        # A new window, also after a lock-out that ended: its failures were paid for.
        counted.failed_since, counted.failures, counted.locked_until = now, 0, None
    counted.failures += 1
    if counted.failures < settings.signin_max_failures:
        session.flush()
        return Counted(None)
    # Locked out, its failures and their start kept: what an administrator is shown.
    counted.locked_until = now + timedelta(seconds=settings.signin_lockout_s)
    session.flush()
    if counted.locked_until <= now:  # DNCQ_SIGNIN_LOCKOUT_S=0: counted, never locked
        return Counted(None)
    return Counted(counted.locked_until, locked_now=True)

