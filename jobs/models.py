"""SQLAlchemy models: the machine registry and the record of jobs."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import JSON, Boolean, DateTime, Integer, String
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column


def utcnow() -> datetime:
    """Now, timezone-aware in UTC."""
    return datetime.now(UTC)


class Base(DeclarativeBase):
    """Declarative base of every dncq table."""


class Machine(Base):
    """A machine of the fleet and how its files are reached."""

    __tablename__ = "machines"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)  # the seed's machineID
    name: Mapped[str] = mapped_column(String(200))
    model: Mapped[str] = mapped_column(String(100))  # controller model, a catalogue row
    transport: Mapped[str] = mapped_column(String(32))
    root: Mapped[str | None] = mapped_column(String(500), default=None)
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # may hold secrets
    encoding: Mapped[str] = mapped_column(String(32), default="utf-8")
    max_concurrent: Mapped[int] = mapped_column(Integer, default=1)
    enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    tags: Mapped[list[str]] = mapped_column(JSON, default=list)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(
        DateTime(timezone=True), default=utcnow, onupdate=utcnow
    )
