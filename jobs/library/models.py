"""The library's tables: programs by folder and name, their versions, machines' folders."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum

from sqlalchemy import BigInteger, Boolean, ForeignKey, Integer, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column, relationship

from jobs.models import Base, UTCDateTime, _enum, utcnow


class VersionState(StrEnum):
    """Whether a version may be rolled out and listed."""

    PENDING = "pending"  # added, waiting for a decision; sent only when asked for by number
    APPROVED = "approved"  # the highest-numbered approved version is the program's current one
    REJECTED = "rejected"  # refused; kept for the record, sent only when asked for by number


class LibraryProgram(Base):
    """A program of the library, by folder and name; deleting it keeps its versions."""

    __tablename__ = "library_programs"
    __table_args__ = (UniqueConstraint("folder", "name"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    folder: Mapped[str] = mapped_column(String(500))  # VIPROS, VIPROS/OLD: `/`-separated
    name: Mapped[str] = mapped_column(String(255))
    deleted: Mapped[bool] = mapped_column(Boolean, default=False)
    deleted_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)

    versions: Mapped[list[LibraryVersion]] = relationship(
        back_populates="program", order_by="LibraryVersion.number",
        cascade="all, delete-orphan")

    @property
    def path(self) -> str:
        """`folder/name`, as the CLI and `dncq send --library` write it."""
        return f"{self.folder}/{self.name}"


class LibraryVersion(Base):
    """One version of a library program: its bytes (a blob), who added it, why, its state."""

    __tablename__ = "library_versions"
    __table_args__ = (UniqueConstraint("program_id", "number"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    program_id: Mapped[int] = mapped_column(
        ForeignKey("library_programs.id", ondelete="CASCADE"), index=True)
    number: Mapped[int] = mapped_column(Integer)  # 1, 2, ... within its program
    sha256: Mapped[str] = mapped_column(String(64), index=True)  # the blob
    size: Mapped[int] = mapped_column(BigInteger)
    state: Mapped[VersionState] = mapped_column(_enum(VersionState),
                                                default=VersionState.PENDING)
    note: Mapped[str] = mapped_column(String(1000), default="")
    source: Mapped[str] = mapped_column(String(200), default="upload")  # restore of v2
    created_by: Mapped[str] = mapped_column(String(100), default="api")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    decided_by: Mapped[str | None] = mapped_column(String(100), default=None)
    decided_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)

    program: Mapped[LibraryProgram] = relationship(back_populates="versions")


class LibraryAssignment(Base):
    """A library folder a machine's programs come from (its `local` listing).

    No foreign key to the machine: removing a machine from the registry and adding it back
    keeps what it was given.
    """

    __tablename__ = "library_assignments"

    machine_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    folder: Mapped[str] = mapped_column(String(500), primary_key=True)  # exactly, not below
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
