"""The auth tables: users, named API keys, the counts of failed sign-ins and wrong keys,
and the audit trail's events."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import JSON, Boolean, Index, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from jobs.auth.roles import Role
from jobs.models import Base, UTCDateTime, _enum, utcnow


class User(Base):
    """A named user of the dashboard: a role, an argon2 password hash, a lock-out count."""

    __tablename__ = "users"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    role: Mapped[Role] = mapped_column(_enum(Role))
    password_hash: Mapped[str] = mapped_column(String(200))  # argon2id, PHC string
    machines: Mapped[list[str] | None] = mapped_column(JSON, default=None)  # None: all
    disabled: Mapped[bool] = mapped_column(Boolean, default=False)
    failed_signins: Mapped[int] = mapped_column(Integer, default=0)  # in the current window
    failed_since: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    locked_until: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    last_signin_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow,
                                                 onupdate=utcnow)


SIGNIN_COUNT_NAME_CHARS = 64


class SignInCount(Base):
    """The failed sign-ins of a name no user has that signs in with a key for its password
    (the admin key's `admin`), from one client address, counted and locked out as a user's
    are."""

    __tablename__ = "signin_counts"

    # The name, and for the key's sign-in the client address: "admin from 10.0.0.7".
    name: Mapped[str] = mapped_column(String(SIGNIN_COUNT_NAME_CHARS), primary_key=True)
    failed_signins: Mapped[int] = mapped_column(Integer, default=0)  # in the current window
    failed_since: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    locked_until: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)


WRONG_KEY_ADDRESS_CHARS = 64


class WrongKeyCount(Base):
    """The wrong API keys one client address sent, counted and locked out as failed
    sign-ins are (`DNCQ_SIGNIN_*`): a locked address has every keyed request refused."""

    __tablename__ = "wrong_key_counts"

    # The client's address; one longer than the column (no IP address is) by its digest.
    address: Mapped[str] = mapped_column(String(WRONG_KEY_ADDRESS_CHARS), primary_key=True)
    failures: Mapped[int] = mapped_column(Integer, default=0)  # in the current window
    failed_since: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    locked_until: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)


class ApiKey(Base):
    """A named API key: only its SHA-256 is kept; the key itself is shown once, when made."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    role: Mapped[Role] = mapped_column(_enum(Role))
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)  # hex SHA-256 of the key
    prefix: Mapped[str] = mapped_column(String(16))  # its first characters, to recognise it
    machines: Mapped[list[str] | None] = mapped_column(JSON, default=None)  # None: all
    created_by: Mapped[str | None] = mapped_column(String(100), default=None)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    last_used_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)


class AuditEvent(Base):
    """One state-changing request, once answered: who, from where, what, and how it ended."""

    __tablename__ = "audit_events"
    __table_args__ = (Index("ix_audit_events_who_at", "who", "at"),
                      Index("ix_audit_events_action_at", "action", "at"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow, index=True)
    who: Mapped[str] = mapped_column(String(100))  # the principal's name; "-" unauthenticated
    kind: Mapped[str] = mapped_column(String(16))  # user, key, admin-key, none, local (host CLI)
    role: Mapped[str | None] = mapped_column(String(16), default=None)
    address: Mapped[str | None] = mapped_column(String(64), default=None)  # the client's IP
    method: Mapped[str] = mapped_column(String(8))
    path: Mapped[str] = mapped_column(String(500))  # without the query: it may hold a key
    status: Mapped[int] = mapped_column(Integer)
    action: Mapped[str] = mapped_column(String(64))  # machines.put, jobs.create, inbox.approve
    target: Mapped[str | None] = mapped_column(String(255), default=None)  # a machine, a job
    detail: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
