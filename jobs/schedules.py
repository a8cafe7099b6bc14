"""Backup schedules: cron, time zone, machines, retention and alerts, stored in the database.

A fixed tick (Celery beat's `dncq.schedule_tick`, or the embedded mode's reaper) looks at
every schedule and starts a backup job for the most recent fire time that has no run yet.
A run is unique per schedule and fire time, so a second beat or a restart cannot double a
backup, and a scheduler that was down over several fire times runs once, not once per
missed night. Fire times before a schedule existed, while it was paused, or before its cron
or time zone last changed never run. The fire times themselves, also on the nights the clocks
change, are jobs.fire_times. What follows a scheduled backup, its retention pass and its
alert, is jobs.backup.follow_up.
"""

from __future__ import annotations

import logging
import re
from datetime import datetime
from pathlib import Path
from typing import Any
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from croniter import CroniterBadDateError, croniter
from pydantic import BaseModel, ConfigDict, Field, field_validator
from sqlalchemy import case, literal, or_, select, tuple_
from sqlalchemy import delete as sa_delete
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from jobs import fire_times, rollout
from jobs import notify as alerts
from jobs.backup import follow_up
from jobs.backup.retention import RetentionPolicy
from jobs.backup_models import Schedule, ScheduleRun
from jobs.db import session_scope, upsert_of
from jobs.errors import ContractError, ErrorCode, first_named
from jobs.fleet import door, registry, sealed
from jobs.fleet.paths import reads_as
from jobs.job_options import JobOptions
from jobs.models import Job, JobKind, UTCDateTime, utcnow
from jobs.settings import Settings

log = logging.getLogger(__name__)


class ScheduleIn(BaseModel):
    """A schedule as the API and CLI give it."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=100, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    cron: str | None = Field(default=None, examples=["0 2 * * *"],
                             description="needed by a new schedule; a change may leave it out")
    timezone: str = "UTC"
    machines: rollout.Selector = Field(default_factory=lambda: rollout.Selector(all=True))
    dirAtCNC: str | None = None
    retention: str = Field(default="", examples=["last=3,daily=14,weekly=8,monthly=12"])
    notify: list[str] = Field(default_factory=list)
    enabled: bool = True

    @field_validator("cron")
    @classmethod
    def _cron(cls, value: str | None) -> str:
        if value is None:  # given as null (left out, it is not looked at)
            raise ValueError("give a cron, or leave it out to keep the schedule's")
        # croniter also reads a sixth field of seconds (and a seventh of years); schedules
        # are looked at every `schedule_tick_s`, so a cron finer than a minute would fire
        # at each look, and "* * * * * *" backed up the fleet every 30 s.
        if not value.strip().startswith("@") and len(value.split()) != 5:
            raise ValueError(f"{value!r}: a cron of five fields, minute hour day month weekday "
                             "(e.g. '0 2 * * *')")
        if not croniter.is_valid(value):
            raise ValueError(f"not a cron expression: {value!r} (e.g. '0 2 * * *')")
        try:  # valid fields can still name a day that never comes (31 February)
            croniter(value, utcnow()).get_next(datetime)
        except CroniterBadDateError:
            raise ValueError(f"{value!r} never fires") from None
        return value

    @field_validator("machines")
    @classmethod
    def _some_machines(cls, value: rollout.Selector) -> rollout.Selector:
        if not (value.all or value.ids or value.tags):
            raise ValueError("no machine selected: give ids, tags or all")
        return value

    @field_validator("dirAtCNC")
    @classmethod
    def _inside_the_root(cls, value: str | None) -> str | None:
        # The full check needs each machine's model; this catches what no machine allows.
        if value is not None and (".." in re.split(r"[\\/]", reads_as(value))
                                  or "\x00" in value):
            raise ValueError(f"{value!r} leaves the machine's root")
        return value

    @field_validator("notify")
    @classmethod
    def _reachable(cls, urls: list[str]) -> list[str]:
        for index, url in enumerate(urls):
            if sealed.is_sealed(url):  # never shown back, so from a copy of a database
                raise ValueError(f"notify[{index}]: {sealed.PREFIX}… is how dncq stores an "
                                 "alert URL, not one it takes: give the URL itself")
            if problem := alerts.problem_with(url):
                raise ValueError(f"notify[{index}]: {problem}")
        return urls

    @field_validator("timezone")
    @classmethod
    def _zone(cls, value: str) -> str:
        try:
            ZoneInfo(value)
        except (ZoneInfoNotFoundError, ValueError):
            raise ValueError(f"unknown time zone {value!r} (e.g. Europe/Berlin)") from None
        return value

    @field_validator("retention")
    @classmethod
    def _retention(cls, value: str) -> str:
        if value:
            RetentionPolicy.parse(value)
        return value


def upsert(*, session: Session, schedule_in: ScheduleIn, data_dir: Path) -> Schedule:
    """Create or change a schedule, in one statement: concurrent saves of one name both land.
    A change keeps what `schedule_in` leaves out: a paused schedule stays paused, and its
    alert URLs, which are never shown back, stay. Those are stored sealed with the keys of
    `data_dir`, as machine secrets are (a webhook's path or query is often its token).

    Raises:
        ContractError: ids or tags no machine has (a typo would back up nothing, every
            night, with no one told before the first run failed); nothing is saved.
    """
    stored = session.get(Schedule, schedule_in.name)
    if stored is None and schedule_in.cron is None:
        raise ContractError(ErrorCode.BAD_PARAMETER, "cron: a new schedule needs one (e.g. "
                            "'0 2 * * *'); the schedule was not saved")
    if found := rollout.unknown(session=session, selector=schedule_in.machines):
        code = ErrorCode.MACHINE_NOT_FOUND if found.ids else ErrorCode.BAD_PARAMETER
        raise ContractError(code, f"{found.message()}; the schedule was not saved")
    if refused := _folder_refused(session, schedule_in, stored):
        code, said = refused
        raise ContractError(code, f"{said}; the schedule was not saved")
    # A change that leaves the cron out still inserts one: SQLite checks NOT NULL on the row
    # it would insert before it takes the conflict's update.
    cron = schedule_in.cron if schedule_in.cron is not None else stored.cron  # type: ignore[union-attr]
    values = {"cron": cron, "timezone": schedule_in.timezone,
              "machines": schedule_in.machines.model_dump(), "dir_at_cnc": schedule_in.dirAtCNC,
              "retention": schedule_in.retention,
              "notify": [sealed.keyring(data_dir).seal(url) for url in schedule_in.notify],
              "enabled": schedule_in.enabled}
    now = utcnow()
    statement = upsert_of(session)(Schedule).values(name=schedule_in.name, created_at=now,
                                                    **values)
    changed: dict[str, Any] = {column: values[column] for field, column in _COLUMNS.items()
                               if field in schedule_in.model_fields_set}
    # Enabled again by this save, or given other times: the fire times before now are not
    # run (those it missed while paused, or its new time earlier today).
    renewed = [getattr(Schedule, c) != getattr(statement.excluded, c)
               for c in ("cron", "timezone") if c in changed]
    if "enabled" in changed:
        renewed.append(Schedule.enabled.is_(False) & statement.excluded.enabled.is_(True))
    if renewed:
        changed["fires_from"] = case((or_(*renewed), literal(now, UTCDateTime())),
                                     else_=Schedule.fires_from)
    session.execute(statement.on_conflict_do_update(index_elements=[Schedule.name],
                                                    set_=changed) if changed  # else its name
                    else statement.on_conflict_do_nothing(index_elements=[Schedule.name]))
    # The row is this transaction's until it commits: a delete meanwhile waits for it.
    schedule = session.get(Schedule, schedule_in.name, populate_existing=True)
    assert schedule is not None
    return schedule


def _folder_refused(session: Session, schedule_in: ScheduleIn, stored: Schedule | None
                    ) -> tuple[ErrorCode, str] | None:
    """The code and words that name the machines the schedule selects, with this change,
    that cannot take its folder, as a target of theirs checks it (each would fail every
    night): its folder not below their roots (20002), or a model that takes no folder
    (20003); None when every one can."""
    given = schedule_in.model_fields_set
    if stored is not None and not {"dirAtCNC", "machines"} & given:
        return None  # a change of its cron or retention alone is not refused for either
    folder = (schedule_in.dirAtCNC if stored is None or "dirAtCNC" in given
              else stored.dir_at_cnc)
    selector = (schedule_in.machines if stored is None or "machines" in given
                else rollout.Selector.model_validate(stored.machines))
    if not folder:
        return None
    try:
        chosen = rollout.select_targets(session=session, selector=selector,
                                        file_name=None, dir_at_cnc=None, sub_dir=None)
    except ContractError:  # no machine yet (an empty fleet, for all): none to check
        return None
    outside, cannot = [], []
    for machine_id, spec in sorted(registry.of_ids(
            session=session, machine_ids=[t.machineID for t in chosen]).items()):
        paths = door.paths_of(spec)
        try:
            paths.resolve(folder, None)
        except ContractError as exc:
            if exc.code is ErrorCode.PATH_OUTSIDE_ROOT:
                outside.append(f"machine {machine_id} ({', '.join(paths.root_names())})")
            else:
                cannot.append((exc.code, f"machine {machine_id}: {exc.status_msg}"))
    if not outside and not cannot:
        return None
    said = ([f"{folder!r} is not below the roots of "
             f"{first_named(outside, registry.HINTED_NAMES)}"] if outside else []) + (
        [first_named([why for _, why in cannot], registry.HINTED_NAMES)] if cannot else [])
    return ErrorCode.PATH_OUTSIDE_ROOT if outside else cannot[0][0], "; ".join(said)


_COLUMNS = {"cron": "cron", "timezone": "timezone", "machines": "machines",
            "dirAtCNC": "dir_at_cnc", "retention": "retention", "notify": "notify",
            "enabled": "enabled"}  # ScheduleIn's fields, and the columns that keep them


def reseal(*, session: Session, data_dir: Path) -> int:
    """Seal every schedule's alert URLs again with the first key, as `registry.reseal` does
    machine secrets (those stored in clear too); returns how many schedules."""
    keys = sealed.keyring(data_dir)
    count = 0
    for schedule in session.scalars(select(Schedule).order_by(Schedule.name)):
        if schedule.notify:
            schedule.notify = [keys.rotated(url) for url in schedule.notify]
            count += 1
    session.flush()
    return count


def get(*, session: Session, name: str) -> Schedule:
    """The schedule, or a 404-worthy error."""
    schedule = session.get(Schedule, name)
    if schedule is None:
        raise no_schedule(name)
    return schedule


def no_schedule(name: str) -> ContractError:
    """158 for a schedule that does not exist (or was removed meanwhile): HTTP 404."""
    return ContractError(ErrorCode.PATH_NOT_FOUND, f"no schedule {name}")


def set_enabled(*, session: Session, name: str, enabled: bool) -> Schedule:
    """Pause or resume a schedule: that column alone (and, on resuming, when), so a save of
    its other fields at the same moment stays; 158 if there is none."""
    schedule = get(session=session, name=name)
    if enabled and not schedule.enabled:
        schedule.fires_from = utcnow()
    schedule.enabled = enabled
    return schedule


def delete(*, session: Session, name: str) -> None:
    """Remove a schedule (its runs with it; its backups stay); 158 if there is none."""
    gone = session.execute(sa_delete(Schedule).where(Schedule.name == name))
    if not gone.rowcount:  # type: ignore[attr-defined]
        raise no_schedule(name)


def view(session: Session, schedule: Schedule, now: datetime | None = None) -> dict[str, Any]:
    """A schedule as the API shows it: notification URLs hidden, its next and last runs
    (both in the schedule's time zone, as its cron reads them)."""
    last = session.scalars(select(ScheduleRun).where(ScheduleRun.schedule_name == schedule.name)
                           .order_by(ScheduleRun.fire_at.desc()).limit(1)).first()
    zone = ZoneInfo(schedule.timezone)
    upcoming = fire_times.next_fire(schedule.cron, zone, now or utcnow()).astimezone(zone)
    return {"name": schedule.name, "cron": schedule.cron, "timezone": schedule.timezone,
            "machines": schedule.machines, "dirAtCNC": schedule.dir_at_cnc,
            "retention": schedule.retention, "notify": len(schedule.notify),
            "enabled": schedule.enabled, "nextRun": upcoming,
            "lastRun": last.fire_at.astimezone(zone) if last else None,
            "lastJob": last.job_id if last else None}


def due_fire(schedule: Schedule, last_fire: datetime | None, now: datetime) -> datetime | None:
    """The most recent fire time not run yet, or None: one run however many were missed,
    and none before `fires_from` (missed while paused, or of times since changed).
    `last_fire` is the last fire time that ran, not the time of a run-now."""
    fire = fire_times.last_fire(schedule.cron, ZoneInfo(schedule.timezone), now)
    since = max(t for t in (last_fire, schedule.created_at, schedule.fires_from)
                if t is not None)
    return fire if fire > since else None


def tick(*, settings: Settings, now: datetime | None = None) -> list[str]:
    """Start every schedule's due backup; returns the jobs started."""
    now = now or utcnow()
    started = []
    url = settings.resolved_database_url
    with session_scope(url) as session:
        schedules = session.scalars(select(Schedule).where(Schedule.enabled.is_(True))).all()
        # Only a run of the fire time itself says it ran: a run-now's, at 02:00:05 before
        # this tick, is not the 02:00 fire.
        due = {s.name: (s, fire) for s in schedules if (fire := due_fire(s, None, now))}
        ran = {(name, fire) for name, fire in session.execute(
            select(ScheduleRun.schedule_name, ScheduleRun.fire_at).where(
                tuple_(ScheduleRun.schedule_name, ScheduleRun.fire_at).in_(
                    [(name, fire) for name, (_, fire) in due.items()])))}
    for name, (schedule, fire) in due.items():
        if (name, fire) in ran:
            continue
        try:
            job_id = _run(settings, schedule.name, fire)
        except ContractError as exc:  # no machine matches its tags any more: say so, go on
            if exc.code is ErrorCode.PATH_NOT_FOUND:
                continue  # removed since this tick read it
            log.warning("schedule %s fired for %s and backed up nothing: %s",
                        schedule.name, fire.isoformat(), exc.status_msg)
            alerts.notify(urls=follow_up.alert_urls(settings, schedule),
                          title=f"dncq: schedule {schedule.name} backed up nothing",
                          body=f"{fire.isoformat()}: {exc.status_msg}")
            continue
        if job_id:
            started.append(job_id)
    return started


def run_now(*, settings: Settings, name: str) -> str:
    """Start the schedule's backup now, outside its cron times.

    Raises:
        ContractError: 158 when there is no such schedule (or it was removed meanwhile),
            20001 when it selects no machine.
    """
    for _ in range(RUN_NOW_TRIES):
        job_id = _run(settings, name, utcnow())
        if job_id is not None:
            return job_id
    raise ContractError(ErrorCode.MACHINE_BUSY, f"schedule {name} is being run; try again")


RUN_NOW_TRIES = 3  # a tick that took the very same microsecond as fire time: take the next


def _run(settings: Settings, name: str, fire: datetime) -> str | None:
    """Start the schedule's backup for `fire`; None when another run took that fire time.

    One transaction records the run, reads the schedule and creates the job, so a schedule
    removed meanwhile either ran (it was there when the job was made) or did not (158):
    the run's row is written first, which takes SQLite's write lock and, on PostgreSQL,
    the foreign key's lock that makes a delete of the schedule wait.
    """
    with session_scope(settings.resolved_database_url) as session:
        run = ScheduleRun(schedule_name=name, fire_at=fire)
        session.add(run)
        try:
            session.flush()
        except IntegrityError:
            session.rollback()
            if session.get(Schedule, name) is None:
                raise no_schedule(name) from None
            return None  # another tick took this fire time
        schedule = get(session=session, name=name)
        try:
            targets = rollout.select_targets(
                session=session, selector=rollout.Selector(**schedule.machines),
                file_name=None, dir_at_cnc=schedule.dir_at_cnc, sub_dir=None)
        except ContractError:
            session.commit()  # the fire is taken though nothing was backed up: one alert
            raise

        def record(job: Job) -> None:
            run.job_id = job.id

        job = rollout.submit(session=session, settings=settings, kind=JobKind.BACKUP,
                             targets=targets, options=JobOptions(),
                             created_by=f"schedule {name}", recorded=record)
        log.info("schedule %s fired for %s: job %s", name, fire.isoformat(), job.id,
                 extra={"job_id": job.id})
        return job.id
