"""The inbox's table: each program a machine sent that was not a request, and its review."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum

from sqlalchemy import BigInteger, Index, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from jobs.models import Base, Message, UTCDateTime, _enum, utcnow


class InboxState(StrEnum):
    """Where a received program is in its review."""

    PENDING = "pending"  # waiting for review
    APPROVED = "approved"  # now a version of a library program (`library_version`)
    REJECTED = "rejected"  # refused; kept until pruned after inbox_rejected_keep_days
    FAILED = "failed"  # a failed reception (no end mark, no name found): kept, capped


class InboxItem(Base):
    """One received program: where and when it came from, what it calls itself, its bytes
    (a library blob), and what was decided.

    No foreign keys to the machine or the job: removing either keeps what was received.
    """

    __tablename__ = "inbox_items"
    __table_args__ = (Index("ix_inbox_items_machine_state", "machine_id", "state"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    machine_id: Mapped[str] = mapped_column(String(64))
    received_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow, index=True)
    name: Mapped[str] = mapped_column(String(255))  # as it came, or as extracted
    program_number: Mapped[str | None] = mapped_column(String(64), default=None)  # O0010
    comment: Mapped[str | None] = mapped_column(String(255), default=None)  # its first one
    folder: Mapped[str] = mapped_column(String(500))  # the library folder it is meant for
    sha256: Mapped[str] = mapped_column(String(64), index=True)  # the blob
    size: Mapped[int] = mapped_column(BigInteger)
    state: Mapped[InboxState] = mapped_column(_enum(InboxState), default=InboxState.PENDING)
    reason: Mapped[str] = mapped_column(Message(1000), default="")  # why failed or rejected
    job_id: Mapped[str | None] = mapped_column(String(32), default=None)  # the request job
    decided_by: Mapped[str | None] = mapped_column(String(100), default=None)
    decided_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    library_version: Mapped[int | None] = mapped_column(Integer, default=None)  # it became

    @property
    def path(self) -> str:
        """`folder/name`: the library program it is meant for (a failed reception may
        have no folder)."""
        return f"{self.folder}/{self.name}" if self.folder else self.name
