"""SQLAlchemy models of stored backups (a ZIP's manifest: its machines and files) and of the
schedules that make them."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Float,
    ForeignKey,
    Integer,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import Mapped, mapped_column, relationship

from jobs.models import Base, Message, UTCDateTime, _enum, utcnow


class BackupStatus(StrEnum):
    """How complete a stored backup is."""

    COMPLETE = "complete"  # every machine backed up
    PARTIAL = "partial"  # some machines failed or files were left out; the manifest says which
    FAILED = "failed"  # no machine could be backed up


class MachineBackupStatus(StrEnum):
    """How completely one machine of a backup was backed up."""

    OK = "ok"  # every file asked for
    PARTIAL = "partial"  # some of its targets failed or files were left out; the rest is in
    FAILED = "failed"  # nothing of it is in the backup


class Backup(Base):
    """A backup ZIP kept in the backup folder, with its manifest in the database."""

    __tablename__ = "backups"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    job_id: Mapped[str | None] = mapped_column(String(32), unique=True, default=None)
    name: Mapped[str] = mapped_column(String(200))  # BackupFiles_<date>-<job>.zip, in backup_dir
    status: Mapped[BackupStatus] = mapped_column(_enum(BackupStatus))
    size: Mapped[int] = mapped_column(BigInteger, default=0)
    sha256: Mapped[str] = mapped_column(String(64), default="")
    file_count: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow, index=True)

    machines: Mapped[list[BackupMachine]] = relationship(cascade="all, delete-orphan",
                                                         order_by="BackupMachine.position")
    files: Mapped[list[BackupFile]] = relationship(cascade="all, delete-orphan",
                                                   order_by="BackupFile.id")


class BackupMachine(Base):
    """One machine of a backup: whether it was backed up."""

    __tablename__ = "backup_machines"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    backup_id: Mapped[str] = mapped_column(ForeignKey("backups.id", ondelete="CASCADE"),
                                           index=True)
    position: Mapped[int] = mapped_column(Integer)
    machine_id: Mapped[str] = mapped_column(String(64))
    machine_name: Mapped[str] = mapped_column(String(200))
    status: Mapped[MachineBackupStatus] = mapped_column(_enum(MachineBackupStatus))
    error_code: Mapped[int] = mapped_column(Integer, default=0)
    error_msg: Mapped[str | None] = mapped_column(Message(1000), default=None)
    # What the backup found but could not take: [{"path", "isDir", "reason"}].
    left_out: Mapped[list[dict[str, Any]]] = mapped_column(JSON, default=list,
                                                           server_default="[]")


class BackupFile(Base):
    """One file of a backup, as the manifest records it."""

    __tablename__ = "backup_files"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    backup_id: Mapped[str] = mapped_column(ForeignKey("backups.id", ondelete="CASCADE"),
                                           index=True)
    machine_id: Mapped[str] = mapped_column(String(64))
    path: Mapped[str] = mapped_column(Text)  # on the machine, in its notation; any length
    archive_path: Mapped[str] = mapped_column(Text)
    size: Mapped[int] = mapped_column(BigInteger)
    mtime: Mapped[float | None] = mapped_column(Float, default=None)  # as 0003 made it
    sha256: Mapped[str] = mapped_column(String(64))


class Schedule(Base):
    """A backup made on a cron schedule, kept by a retention policy."""

    __tablename__ = "schedules"

    name: Mapped[str] = mapped_column(String(100), primary_key=True)
    cron: Mapped[str] = mapped_column(String(100))  # minute hour day month weekday
    timezone: Mapped[str] = mapped_column(String(64), default="UTC")
    machines: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # ids, tags, all
    dir_at_cnc: Mapped[str | None] = mapped_column(Text, default=None)
    retention: Mapped[str] = mapped_column(String(200), default="")  # "last=7,daily=14"
    notify: Mapped[list[str]] = mapped_column(JSON, default=list)  # URLs; may hold secrets
    enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    # Fire times before it never run: when it was enabled again after a pause, or its cron
    # or time zone changed (a nightly 02:00 moved to 03:00 at 14:00 runs tonight, not now).
    fires_from: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)


class ScheduleRun(Base):
    """One fire of a schedule; unique per fire time, so no fire runs twice."""

    __tablename__ = "schedule_runs"
    __table_args__ = (UniqueConstraint("schedule_name", "fire_at"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    schedule_name: Mapped[str] = mapped_column(
        ForeignKey("schedules.name", ondelete="CASCADE"), index=True)
    fire_at: Mapped[datetime] = mapped_column(UTCDateTime())
    job_id: Mapped[str | None] = mapped_column(String(32), default=None, index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    # When its backup's retention pass and alert were done (jobs.backup.follow_up.after_backup):
    # None while they are owed, also to an assembly delivered again after a lost worker.
    followed_up_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
