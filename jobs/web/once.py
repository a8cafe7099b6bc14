"""Forms that start something are sent once.

Such a form carries a one-time key (`once_field` in _macros.html), claimed when the form
is sent: a second click on its button, or the same page sent again from the browser's
history, finds the key used and starts nothing a second time. A preview sent from the
same form (its `action` is `preview`) changes nothing and claims nothing.
"""

from __future__ import annotations

import secrets
from datetime import timedelta

from sqlalchemy import delete
from sqlalchemy.exc import IntegrityError

from jobs.db import session_scope
from jobs.models import utcnow
from jobs.web.models import WebFormUse

FIELD = "form_key"
KEPT = timedelta(days=1)  # a page older than that is out of date for its CSRF token anyway


def new_key() -> str:
    """A key for one form, as the page is rendered."""
    return secrets.token_urlsafe(24)


def claim(url: str, key: str) -> bool:
    """True the first time `key` is sent, False after; committed at once, so that the
    claim stands whatever the form's request then answers (its answer is a new page,
    with a new key)."""
    now = utcnow()
    try:
        with session_scope(url) as session:
            session.execute(delete(WebFormUse).where(WebFormUse.used_at < now - KEPT))
            session.add(WebFormUse(form_key=key[:64], used_at=now))
    except IntegrityError:
        return False
    return True
