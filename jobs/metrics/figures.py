"""The fleet's figures as the record holds them now, in a handful of GROUP BY queries.

Nothing here loads rows one by one: every figure is an aggregate computed by the database,
so that a scrape costs the same few queries at 100 targets as at 100,000. Durations are
put into fixed buckets in SQL (`_histogram`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Select, case, extract, func, select, true
from sqlalchemy.orm import Session

from jobs.backup_models import Backup, BackupFile
from jobs.job_views import none_begun
from jobs.models import (
    Job,
    JobKind,
    JobState,
    Machine,
    MachineCheck,
    MachineLease,
    Payload,
    Run,
    RunState,
    Target,
    TargetState,
    utcnow,
)

# Upper bounds (seconds) of the duration buckets: a small send takes well under a second,
# a large one or a backup of a big machine minutes; a drip-fed program is not a target here.
TARGET_BUCKETS_S: tuple[float, ...] = (0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 900,
                                       1800, 3600)
BACKUP_BUCKETS_S: tuple[float, ...] = (1, 5, 10, 30, 60, 120, 300, 900, 1800, 3600, 7200,
                                       14400)

_FINAL = [s for s in TargetState if s.final]


@dataclass
class Histogram:
    """Observations in fixed buckets: `counts[i]` of them took at most `bounds[i]` seconds."""

    bounds: tuple[float, ...]
    counts: list[int]  # cumulative, one per bound
    count: int = 0  # every observation (the +Inf bucket)
    sum_s: float = 0.0


@dataclass
class TargetFigures:
    """Targets of one job kind in one state."""

    count: int = 0
    bytes_moved: int = 0
    retries: int = 0  # attempts beyond the first
    waiting: int = 0  # pending and not queued: their machine was busy when they were due


@dataclass
class LastBackup:
    """The newest stored backup."""

    size: int
    created_at: datetime
    duration_s: float | None  # its job's, from creation to its last target; None if pruned


@dataclass
class RunningRun:
    """A drip-feed run the machine is executing."""

    machine_id: str
    lines_per_s: float  # lines sent since it started, over the time to its last progress


@dataclass
class Figures:
    """Everything `/metrics` shows of the fleet, read in one go."""

    jobs: dict[tuple[str, str], int] = field(default_factory=dict)  # (kind, state)
    targets: dict[tuple[str, str], TargetFigures] = field(default_factory=dict)
    target_durations: dict[str, Histogram] = field(default_factory=dict)  # by kind
    backup_file_bytes: int = 0  # what backups read from the machines
    machines: dict[tuple[str, bool], int] = field(default_factory=dict)  # (transport, enabled)
    machines_online: int = 0  # enabled ones that answered their last check, or drip-feed now
    machines_offline: int = 0  # enabled ones whose last check found them unreachable
    leases: dict[str, int] = field(default_factory=dict)  # by kind of group: job, api, listen
    backups: dict[str, int] = field(default_factory=dict)  # by status
    backup_bytes: int = 0  # of the kept ZIPs
    last_backup: LastBackup | None = None
    backup_durations: Histogram = field(
        default_factory=lambda: Histogram(BACKUP_BUCKETS_S, [0] * len(BACKUP_BUCKETS_S)))
    runs: dict[str, int] = field(default_factory=dict)  # by state
    run_lines_sent: int = 0  # of every run in the record
    running: list[RunningRun] = field(default_factory=list)


def read(*, session: Session, check_max_age_s: float | None = None) -> Figures:
    """The figures of the fleet as the database has them now; a machine check older than
    `check_max_age_s` counts as none."""
    figures = Figures()
    seconds = _seconds_between(session)
    _jobs(session, figures)
    _targets(session, figures, seconds)
    figures.backup_file_bytes = int(session.scalar(
        select(func.coalesce(func.sum(BackupFile.size), 0))) or 0)
    for transport, enabled, n in session.execute(
            select(Machine.transport, Machine.enabled, func.count())
            .group_by(Machine.transport, Machine.enabled)):
        figures.machines[(transport, bool(enabled))] = int(n)
    _reachable(session, figures, check_max_age_s)
    for group, n in session.execute(  # a group per lease at most: as many as machine slots
            select(MachineLease.group, func.count()).where(MachineLease.expires_at > utcnow())
            .group_by(MachineLease.group)):
        kind = group.partition(":")[0]
        figures.leases[kind] = figures.leases.get(kind, 0) + int(n)
    _backups(session, figures, seconds)
    _runs(session, figures, seconds)
    return figures


def _reachable(session: Session, figures: Figures, max_age_s: float | None) -> None:
    """Enabled machines online and offline by their last check (jobs.fleet.checks.state);
    one that is drip-feeding is online whatever its last check said."""
    running = select(Run.machine_id).where(Run.state == RunState.RUNNING)
    recent = MachineCheck.checked_at >= utcnow() - timedelta(seconds=max_age_s) \
        if max_age_s is not None else true()
    state = case((Machine.id.in_(running), "online"),
                 (MachineCheck.machine_id.is_(None) | ~recent, "unchecked"),
                 (MachineCheck.reachable, "online"), else_="offline")
    counted = {str(name): int(n) for name, n in session.execute(
        select(state, func.count()).select_from(Machine)
        .outerjoin(MachineCheck, MachineCheck.machine_id == Machine.id)
        .where(Machine.enabled).group_by(state))}
    figures.machines_online = int(counted.get("online", 0))
    figures.machines_offline = int(counted.get("offline", 0))


def _jobs(session: Session, figures: Figures) -> None:
    for kind, state, n in session.execute(
            select(Job.kind, Job.state, func.count()).group_by(Job.kind, Job.state)):
        figures.jobs[(kind.value, state.value)] = int(n)
    # One recorded running none of whose targets has begun is queued, as the API shows it.
    for kind, n in session.execute(
            select(Job.kind, func.count()).where(Job.state == JobState.RUNNING,
                                                 none_begun(Job.id)).group_by(Job.kind)):
        figures.jobs[(kind.value, JobState.RUNNING.value)] -= int(n)
        queued = (kind.value, JobState.QUEUED.value)
        figures.jobs[queued] = figures.jobs.get(queued, 0) + int(n)


def _targets(session: Session, figures: Figures, seconds: Any) -> None:
    """Targets by kind and state, and their durations, in one pass over the targets."""
    timed = Target.state.in_(_FINAL) & Target.started_at.is_not(None) \
        & Target.finished_at.is_not(None)
    rows = _once_per_row(session, select(
        Target.job_id, Target.state, Target.payload_id, Target.bytes_done,
        case((Target.attempts > 1, Target.attempts - 1), else_=0).label("retries"),
        case(((Target.state == TargetState.PENDING) & Target.dispatched_at.is_(None), 1),
             else_=0).label("waiting"),
        case((timed, seconds(Target.started_at, Target.finished_at)), else_=None).label("d")))
    # Grouped by job, state and own payload first; the few groups are then joined to their
    # jobs and payloads.
    groups = select(
        rows.c.job_id, rows.c.state, rows.c.payload_id, func.count().label("n"),
        func.sum(rows.c.bytes_done).label("reported"), func.sum(rows.c.retries).label("retries"),
        func.sum(rows.c.waiting).label("waiting"), func.count(rows.c.d).label("timed"),
        func.sum(rows.c.d).label("d_sum"),
        *[func.sum(case((rows.c.d <= bound, 1), else_=0)).label(f"le{i}")
          for i, bound in enumerate(TARGET_BUCKETS_S)],
    ).group_by(rows.c.job_id, rows.c.state, rows.c.payload_id).subquery()
    # A finished send moved its payload (small ones report no progress, large ones at most
    # its size); one that failed on the way, what it reported before it failed.
    size = func.coalesce(Payload.size, 0)
    moved = case((groups.c.state == TargetState.SUCCEEDED, groups.c.n * size),
                 (groups.c.state.in_([TargetState.FAILED, TargetState.CANCELLED]),
                  groups.c.reported), else_=0)
    query = (select(Job.kind, groups.c.state, func.sum(groups.c.n),
                    func.coalesce(func.sum(moved), 0), func.sum(groups.c.retries),
                    func.sum(groups.c.waiting), func.sum(groups.c.timed),
                    func.sum(groups.c.d_sum),
                    *[func.sum(groups.c[f"le{i}"]) for i in range(len(TARGET_BUCKETS_S))])
             .select_from(groups).join(Job, Job.id == groups.c.job_id)
             .outerjoin(Payload, Payload.id == func.coalesce(groups.c.payload_id, Job.payload_id))
             .group_by(Job.kind, groups.c.state))
    for kind, state, n, moved_bytes, retried, waits, n_timed, d_sum, *counts in \
            session.execute(query):
        figures.targets[(kind.value, TargetState(state).value)] = TargetFigures(
            count=int(n), bytes_moved=int(moved_bytes), retries=int(retried or 0),
            waiting=int(waits or 0))
        if n_timed:
            histogram = figures.target_durations.setdefault(kind.value, Histogram(
                TARGET_BUCKETS_S, [0] * len(TARGET_BUCKETS_S)))
            histogram.count += int(n_timed)
            histogram.sum_s += float(d_sum or 0)
            histogram.counts = [a + int(b or 0) for a, b in zip(histogram.counts, counts,
                                                                strict=True)]


def _backups(session: Session, figures: Figures, seconds: Any) -> None:
    for status, n, size in session.execute(
            select(Backup.status, func.count(), func.coalesce(func.sum(Backup.size), 0))
            .group_by(Backup.status)):
        figures.backups[status.value] = int(n)
        figures.backup_bytes += int(size)
    took = seconds(Job.created_at, Job.finished_at)
    last = session.execute(
        select(Backup.size, Backup.created_at, took).outerjoin(Job, Job.id == Backup.job_id)
        .order_by(Backup.created_at.desc()).limit(1)).one_or_none()
    if last is not None:
        figures.last_backup = LastBackup(size=int(last[0]), created_at=last[1],
                                         duration_s=None if last[2] is None else float(last[2]))
    by_kind = _histograms(session, BACKUP_BUCKETS_S, select(Job.id.label("job_id"), took.label("d"))
                          .select_from(Backup).join(Job, Job.id == Backup.job_id)
                          .where(Job.finished_at.is_not(None)))
    if JobKind.BACKUP.value in by_kind:
        figures.backup_durations = by_kind[JobKind.BACKUP.value]


def _runs(session: Session, figures: Figures, seconds: Any) -> None:
    for state, n, lines in session.execute(
            select(Run.state, func.count(), func.coalesce(func.sum(Run.lines_sent), 0))
            .group_by(Run.state)):
        figures.runs[state.value] = int(n)
        figures.run_lines_sent += int(lines)
    # As many running runs as machines at most.
    for machine_id, lines, took in session.execute(
            select(Run.machine_id, Run.lines_sent, seconds(Run.started_at, Run.updated_at))
            .where(Run.state == RunState.RUNNING, Run.started_at.is_not(None))):
        rate = float(lines) / float(took) if took and float(took) > 0 else 0.0
        figures.running.append(RunningRun(machine_id=machine_id, lines_per_s=rate))


def _histograms(session: Session, bounds: tuple[float, ...],
                durations: Select[Any]) -> dict[str, Histogram]:
    """Durations put in buckets by the database, one histogram per job kind; `durations`
    selects a `job_id` and its seconds `d`, once per observation."""
    rows = _once_per_row(session, durations)
    buckets = [func.coalesce(func.sum(case((rows.c.d <= bound, 1), else_=0)), 0)
               for bound in bounds]
    query = (select(Job.kind, *buckets, func.count(), func.coalesce(func.sum(rows.c.d), 0.0))
             .select_from(rows).join(Job, Job.id == rows.c.job_id).group_by(Job.kind))
    found = {}
    for row in session.execute(query):
        kind, *counts, n, total = row
        found[kind.value] = Histogram(bounds, [int(c) for c in counts], int(n), float(total))
    return found


def _once_per_row(session: Session, query: Select[Any]) -> Any:
    """`query` as a subquery whose columns are worked out once per row, however often the
    query around it uses them."""
    # Both databases merge a subquery into the query around it, repeating its expressions
    # (SQLite's julianday() parses text each time); a LIMIT or an OFFSET keeps it apart.
    if session.get_bind().dialect.name == "sqlite":
        query = query.limit(-1)
    else:
        query = query.offset(0)
    return query.subquery()


def _seconds_between(session: Session) -> Any:
    """A function making the SQL expression of the seconds from one timestamp to another."""
    if session.get_bind().dialect.name == "postgresql":
        return lambda start, end: extract("epoch", end - start)
    # SQLite keeps timestamps as text, which julianday() reads to a fraction of a day.
    return lambda start, end: (func.julianday(end) - func.julianday(start)) * 86400.0
