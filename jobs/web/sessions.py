"""Browser sessions: begun at sign-in, found by their cookie, ended at sign-out or expiry.

The cookie carries a random token; the table keeps only its SHA-256, so a copy of the
database signs nobody in. Each session has its own CSRF token, which every state-changing
form or fetch must carry.
"""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass
from datetime import timedelta

from sqlalchemy import delete
from sqlalchemy.orm import Session

from jobs.db import rowcount
from jobs.models import utcnow
from jobs.settings import Settings
from jobs.web.models import WebSession

COOKIE = "dncq_session"
TOKEN_BYTES = 32
TOUCH_EVERY_S = 60.0  # last_seen_at is written at most this often: pages read, not write


@dataclass(frozen=True)
class Begun:
    """A new session: the token for the cookie (never stored), and its row."""

    token: str
    row: WebSession


def _hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def begin(*, session: Session, settings: Settings, user_name: str,
          address: str | None) -> Begun:
    """A session for `user_name`, valid at most `web_session_max_s` from now."""
    token = secrets.token_urlsafe(TOKEN_BYTES)
    now = utcnow()
    session.execute(delete(WebSession).where(  # sessions nobody came back to end here
        (WebSession.expires_at <= now)
        | (WebSession.last_seen_at <= now - timedelta(seconds=settings.web_session_idle_s))))
    row = WebSession(token_hash=_hash(token), user_name=user_name,
                     csrf_token=secrets.token_urlsafe(TOKEN_BYTES), created_at=now,
                     last_seen_at=now, address=address,
                     expires_at=now + timedelta(seconds=settings.web_session_max_s))
    session.add(row)
    session.flush()
    return Begun(token, row)


def find(*, session: Session, settings: Settings, token: str | None) -> WebSession | None:
    """The live session of a cookie's token; an expired one is removed and None returned."""
    if not token:
        return None
    row = session.get(WebSession, _hash(token))
    if row is None:
        return None
    now = utcnow()
    idle_s = (now - row.last_seen_at).total_seconds()
    if now >= row.expires_at or idle_s >= settings.web_session_idle_s:
        session.delete(row)
        return None
    if idle_s >= TOUCH_EVERY_S:
        row.last_seen_at = now
    return row


def end(*, session: Session, token: str | None) -> None:
    """Remove the session of a cookie's token (sign-out), if there is one."""
    if token:
        session.execute(delete(WebSession).where(WebSession.token_hash == _hash(token)))


def end_all_of(*, session: Session, user_name: str) -> int:
    """Remove every session of a user (removed or disabled); returns how many."""
    return rowcount(session.execute(delete(WebSession).where(WebSession.user_name == user_name)))


def csrf_matches(row: WebSession, given: str | None) -> bool:
    """Whether a form's or header's token is the session's."""
    return given is not None and secrets.compare_digest(given.encode(), row.csrf_token.encode())
