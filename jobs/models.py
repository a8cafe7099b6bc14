"""SQLAlchemy models: the machine registry and the record of jobs."""

from __future__ import annotations

from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    ColumnElement,
    DateTime,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
    literal_column,
    text,
)
from sqlalchemy import Enum as SAEnum
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator


def utcnow() -> datetime:
    """Now, timezone-aware in UTC."""
    return datetime.now(UTC)


def utc_text(moment: datetime) -> str:
    """`2026-12-06 05:46 UTC`: a moment as dncq writes it into a message or a generated
    text, in UTC and saying so (a naive moment is taken as UTC, as the database keeps it)."""
    if moment.tzinfo is not None:
        moment = moment.astimezone(UTC)
    return f"{moment:%Y-%m-%d %H:%M} UTC"


class UTCDateTime(TypeDecorator[datetime]):
    """A UTC timestamp that comes back timezone-aware on every database (SQLite forgets)."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is not None:
            value = value.astimezone(UTC).replace(tzinfo=None)
        return value

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        return value.replace(tzinfo=UTC) if value is not None else None


class Message(TypeDecorator[str]):
    """Text that machines and requests say (an FTP server's reply, a path), stored cut to the
    column's length: PostgreSQL refuses a longer value, and with it every result of the same
    transaction (jobs.run.group_commit). The start is kept and the cut marked with `…`."""

    impl = String
    cache_ok = True

    def __init__(self, length: int) -> None:
        super().__init__(length)
        self.length = length  # in characters, as PostgreSQL's varchar counts

    def process_bind_param(self, value: str | None, dialect: Any) -> str | None:
        if value is not None and len(value) > self.length:
            return value[:self.length - 1] + "…"
        return value


class Base(DeclarativeBase):
    """Declarative base of every dncq table."""


# Request settings set: neither SQL NULL nor JSON null (what an unset JSON column holds).
TAKES_REQUESTS = "requests IS NOT NULL AND CAST(requests AS TEXT) != 'null'"


class Machine(Base):
    """A machine of the fleet and how its files are reached."""

    __tablename__ = "machines"
    __table_args__ = (
        # The few machines with request settings, which every worker asks for every few
        # seconds (jobs.fleet.registry.taking_requests), among a fleet of 100,000.
        Index("ix_machines_taking_requests", "id",
              postgresql_where=text(TAKES_REQUESTS), sqlite_where=text(TAKES_REQUESTS)),
    )

    id: Mapped[str] = mapped_column(String(64), primary_key=True)  # the contract's machineID
    name: Mapped[str] = mapped_column(String(200))
    model: Mapped[str] = mapped_column(String(100))  # controller model, a catalogue row
    transport: Mapped[str] = mapped_column(String(32))
    root: Mapped[str | None] = mapped_column(Text, default=None)  # as long as fleet.paths allows
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # may hold secrets
    encoding: Mapped[str] = mapped_column(String(32), default="utf-8")
    max_concurrent: Mapped[int] = mapped_column(Integer, default=1)
    enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    tags: Mapped[list[str]] = mapped_column(JSON, default=list)
    # What the machine's operator may ask from the control (jobs.fleet.request_settings), as given.
    requests: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(
        UTCDateTime(), default=utcnow, onupdate=utcnow
    )


def _enum(enum: type[StrEnum]) -> SAEnum:
    """A state column stored as the enum's values ("pending"), not its member names."""
    return SAEnum(enum, native_enum=False, length=16,
                  values_callable=lambda e: [member.value for member in e])


class JobKind(StrEnum):
    """What a job does to each of its targets."""

    SEND = "send"  # put one payload on every target
    DELETE = "delete"  # delete one file on every target
    BACKUP = "backup"  # fetch files and folders of every target into one stored ZIP
    RESTORE = "restore"  # put files back (of a stored backup, or a replace job's old files)
    DNC_RUN = "dnc_run"  # drip-feed a program to each target while it runs (a Run per target)
    REQUEST = "request"  # what a machine's operator sent: a request, or a program to receive


class JobState(StrEnum):
    """Where a job stands; derived from its targets by jobs.service."""

    QUEUED = "queued"  # no target started yet
    RUNNING = "running"  # some target not final
    SUCCEEDED = "succeeded"  # every target succeeded (or was skipped as identical)
    FAILED = "failed"  # every target final, at least one failed or was cancelled
    CANCELLED = "cancelled"  # cancelled before every target finished


class TargetState(StrEnum):
    """Where one target stands."""

    PENDING = "pending"  # waiting for its machine (or for its retry time)
    RUNNING = "running"  # a runner holds it; `lease_until` says until when
    SUCCEEDED = "succeeded"  # errorCode 0
    SKIPPED = "skipped"  # skip_identical: the same bytes were already there
    FAILED = "failed"  # its errorCode says why; `retry` runs it again
    CANCELLED = "cancelled"  # 20015: on request, or a rollout aborted after too many failures

    @property
    def final(self) -> bool:
        """No runner will touch this target again (unless retried on request)."""
        return self not in ACTIVE_STATES


ACTIVE_STATES = (TargetState.PENDING, TargetState.RUNNING)
"""States a runner may still move a target out of."""

# The conditions of the partial indexes on one state (ix_targets_*; see `state_is`).
PENDING_WHERE = f"state = '{TargetState.PENDING.value}'"
RUNNING_WHERE = f"state = '{TargetState.RUNNING.value}'"


class Payload(Base):
    """File content stored once and shared by every target that sends it."""

    __tablename__ = "payloads"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)  # SHA-256, hex
    size: Mapped[int] = mapped_column(BigInteger)
    data: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class Job(Base):
    """One batch request and its options."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    kind: Mapped[JobKind] = mapped_column(_enum(JobKind))
    state: Mapped[JobState] = mapped_column(_enum(JobState), default=JobState.QUEUED, index=True)
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    payload_id: Mapped[str | None] = mapped_column(ForeignKey("payloads.id"), default=None)
    file_name: Mapped[str | None] = mapped_column(String(255), default=None)
    created_by: Mapped[str] = mapped_column(String(100), default="api")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow,
                                                 index=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    retry_of: Mapped[str | None] = mapped_column(String(32), default=None)
    # The library version a send job sent (jobs.library); no foreign key, as for runs.
    library_version_id: Mapped[int | None] = mapped_column(Integer, default=None, index=True)

    targets: Mapped[list[Target]] = relationship(
        back_populates="job", order_by="Target.position", cascade="all, delete-orphan"
    )


class Target(Base):
    """One target of a job: a machine and where on it; its latest result."""

    __tablename__ = "targets"
    __table_args__ = (
        UniqueConstraint("job_id", "position"),
        Index("ix_targets_machine_state", "machine_id", "state"),
        Index("ix_targets_job_state", "job_id", "state"),
        # What every reaper asks every few seconds, among a history of millions of targets:
        # which pending ones were queued long ago, which running ones' leases ran out
        # (read through `state_is`, so that the planner sees the state).
        Index("ix_targets_pending_queued_at", "dispatched_at",
              postgresql_where=text(PENDING_WHERE), sqlite_where=text(PENDING_WHERE)),
        Index("ix_targets_running_lease", "lease_until",
              postgresql_where=text(RUNNING_WHERE), sqlite_where=text(RUNNING_WHERE)),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"))
    position: Mapped[int] = mapped_column(Integer)  # index in the request's targets
    machine_id: Mapped[str] = mapped_column(String(64))
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # fileName, dirAtCNC...
    payload_id: Mapped[str | None] = mapped_column(ForeignKey("payloads.id"), default=None)
    state: Mapped[TargetState] = mapped_column(_enum(TargetState), default=TargetState.PENDING)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    error_code: Mapped[int | None] = mapped_column(Integer, default=None)
    error_msg: Mapped[str | None] = mapped_column(Message(500), default=None)
    status_msg: Mapped[str | None] = mapped_column(Message(1000), default=None)
    next_attempt_at: Mapped[datetime | None] = mapped_column(UTCDateTime(),
                                                             default=None)
    dispatched_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    lease_until: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    bytes_done: Mapped[int] = mapped_column(BigInteger, default=0)
    bytes_total: Mapped[int | None] = mapped_column(BigInteger, default=None)
    replaced_payload_id: Mapped[str | None] = mapped_column(ForeignKey("payloads.id"),
                                                            default=None)
    claimed_by: Mapped[str | None] = mapped_column(String(200), default=None)  # host:pid
    # an attempt was cut off (its worker lost, or its connection) and may have done its work
    interrupted: Mapped[bool] = mapped_column(Boolean, default=False)
    # A retry on request (`dncq retry`): the attempts made before it, and when it was asked.
    # Its own tries count from there, as a new job's would: its max_attempts, its backoff,
    # its deliver_within window. None: never retried on request.
    retried_after: Mapped[int | None] = mapped_column(Integer, default=None)
    retried_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)

    job: Mapped[Job] = relationship(back_populates="targets")
    history: Mapped[list[Attempt]] = relationship(
        order_by="Attempt.number", cascade="all, delete-orphan"
    )


def state_is(state: TargetState) -> ColumnElement[bool]:
    """`Target.state == state` with the state written into the statement: a partial index
    on a state (ix_targets_pending_queued_at, ix_targets_running_lease) serves only a
    statement whose plan knows the value, and a prepared statement's plan may not."""
    return Target.state == literal_column(f"'{state.value}'")


class Attempt(Base):
    """One try of one target, kept for the record."""

    __tablename__ = "attempts"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    target_id: Mapped[int] = mapped_column(ForeignKey("targets.id", ondelete="CASCADE"),
                                           index=True)
    number: Mapped[int] = mapped_column(Integer)
    worker: Mapped[str] = mapped_column(String(200), default="")
    started_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    error_code: Mapped[int | None] = mapped_column(Integer, default=None)
    error_msg: Mapped[str | None] = mapped_column(Message(1000), default=None)


class RunState(StrEnum):
    """Where a drip-feed run stands."""

    QUEUED = "queued"  # waiting for its machine (or for the control to be put in DNC mode)
    RUNNING = "running"  # the machine is executing it; `last_line` moves
    SUCCEEDED = "succeeded"  # the machine executed the last line
    STOPPED = "stopped"  # stopped on request: the machine was reset
    FAILED = "failed"  # link lost, worker lost or refused; `last_line` says where it was
    CANCELLED = "cancelled"  # cancelled before it started: the machine never saw it


class Run(Base):
    """One drip-feed run of a program on a machine: the run history.

    Kept apart from the job (no foreign key): pruning old jobs keeps the record of what
    ran where, which the program listing reads.
    """

    __tablename__ = "runs"
    __table_args__ = (UniqueConstraint("job_id", "machine_id"),
                      Index("ix_runs_machine_started", "machine_id", "started_at"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(String(32), index=True)
    position: Mapped[int] = mapped_column(Integer)  # the job's target it runs (one per machine)
    machine_id: Mapped[str] = mapped_column(String(64))
    program_name: Mapped[str] = mapped_column(String(255), index=True)
    program_id: Mapped[str] = mapped_column(String(64))  # SHA-256 of the stored program
    state: Mapped[RunState] = mapped_column(_enum(RunState), default=RunState.QUEUED)
    started_by: Mapped[str] = mapped_column(String(100), default="api")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    ended_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    start_line: Mapped[int] = mapped_column(Integer, default=1)  # > 1: restarted from a block
    restart_from: Mapped[str | None] = mapped_column(String(100), default=None)  # as asked
    header: Mapped[list[str]] = mapped_column(JSON, default=list)  # sent before start_line
    lines_total: Mapped[int] = mapped_column(BigInteger, default=0)  # header included
    lines_sent: Mapped[int] = mapped_column(BigInteger, default=0)
    last_line: Mapped[int] = mapped_column(BigInteger, default=0)  # of the program's file
    stop_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    stopped_by: Mapped[str | None] = mapped_column(String(100), default=None)  # who asked it
    message: Mapped[str | None] = mapped_column(Message(1000), default=None)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class MachineCheck(Base):
    """A machine's last check: whether it answered, and what `checks.check` found."""

    __tablename__ = "machine_checks"

    machine_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    checked_at: Mapped[datetime] = mapped_column(UTCDateTime())
    reachable: Mapped[bool] = mapped_column(Boolean)
    found: Mapped[dict[str, Any]] = mapped_column(JSON)  # latency, free space, error, link


class MachineLease(Base):
    """A slot of a machine's concurrency limit, held until `expires_at` unless renewed."""

    __tablename__ = "machine_leases"
    __table_args__ = (UniqueConstraint("machine_id", "group"),)

    machine_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    slot: Mapped[int] = mapped_column(Integer, primary_key=True)
    group: Mapped[str] = mapped_column(String(100))  # "job:<id>" or "api:<uuid>"
    holder: Mapped[str] = mapped_column(String(100))  # one acquisition: renew and release by it
    expires_at: Mapped[datetime] = mapped_column(UTCDateTime())
