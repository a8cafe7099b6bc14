"""The dashboard's table: signed-in browser sessions."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import String
from sqlalchemy.orm import Mapped, mapped_column

from jobs.models import Base, UTCDateTime, utcnow


class WebSession(Base):
    """One signed-in browser: the hash of its cookie's token, whose it is, its CSRF token."""

    __tablename__ = "web_sessions"

    token_hash: Mapped[str] = mapped_column(String(64), primary_key=True)  # SHA-256, hex
    user_name: Mapped[str] = mapped_column(String(100), index=True)
    csrf_token: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(UTCDateTime(), index=True)  # at the latest
    last_seen_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    address: Mapped[str | None] = mapped_column(String(100), default=None)


class WebFormUse(Base):
    """A form that starts something, sent once: its one-time key, kept for a day, so that
    a second click, or the same form sent again from the browser's history, starts
    nothing a second time."""

    __tablename__ = "web_form_uses"

    form_key: Mapped[str] = mapped_column(String(64), primary_key=True)
    used_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow, index=True)
