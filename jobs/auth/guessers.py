"""Who a guess at a key is counted against (the client's address, or for IPv6 its /64),
a guesser's count row held for counting, and the counts of guessers whose window and
lock-out have ended, removed.

One IPv6 host is given a whole /64 network, and picks a new address in it at will: counted
per address, its guesses would never add up to a lock-out.
"""

from __future__ import annotations

import ipaddress
from datetime import timedelta
from typing import Any

from sqlalchemy import delete, or_, select
from sqlalchemy.orm import InstrumentedAttribute, Session

from jobs import db
from jobs.models import utcnow

IPV6_PREFIX = 64  # what one host (a home, a server's interface) is given


def guesser_of(address: str) -> str:
    """`address` as its guesses are counted: an IPv4 address itself, an IPv6 one as its /64
    (`2001:db8:1:2::/64`), an IPv4-mapped IPv6 one as the IPv4 address; anything that is no
    IP address (a test client's name) as it is."""
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])  # without a link-local zone
    except ValueError:
        return address
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, IPV6_PREFIX), strict=False))
    return str(ip)


def held_count(session: Session, key: InstrumentedAttribute[str], name: str, *,
               window_s: float, **empty: int) -> Any:
    """The count row of `key`'s table named `name`, made (with the `empty` counts) if it is
    not there, held to the end of the transaction as others left it: two guesses at the same
    moment, in this process or another, each count. Making a row removes the guessers'
    rows that ended (`forget_ended`)."""
    table: Any = key.class_
    db.write_first(session)  # then the row made, if it is not, and held as others left it
    while True:  # again if another count removed it as ended in between
        made = session.execute(db.upsert_of(session)(table).values(
            {key.key: name, **empty}).on_conflict_do_nothing())
        if made.rowcount:  # type: ignore[attr-defined]
            forget_ended(session, key, besides=name, window_s=window_s)
        counted = session.scalar(db.held(session, select(table).where(key == name)))
        if counted is not None:
            return counted


def forget_ended(session: Session, key: InstrumentedAttribute[str], *, besides: str,
                 window_s: float) -> None:
    """Remove the rows of `key`'s table (a count with `failed_since` and `locked_until`)
    whose window and lock-out have both ended, all but `besides`'s. Called when a guesser is
    first counted, so that the table holds only the last window's guessers, however many
    addresses they send from."""
    table: Any = key.class_
    now = utcnow()
    session.execute(delete(table).where(
        key != besides,
        # A row just made (both empty) may be another count's, about to be held: kept.
        or_(table.failed_since.is_not(None), table.locked_until.is_not(None)),
        or_(table.failed_since.is_(None),
            table.failed_since < now - timedelta(seconds=window_s)),
        or_(table.locked_until.is_(None), table.locked_until <= now)))
