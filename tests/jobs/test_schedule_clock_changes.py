"""Schedules on the nights the clocks change: one backup a night, one an hour for an hourly
schedule, the same whichever croniter is installed, and the next run said as the clock
shows it."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any
from zoneinfo import ZoneInfo

import pytest
from croniter import croniter
from sqlalchemy import select, update

from jobs import db, fire_times, schedules
from jobs.backup_models import Schedule, ScheduleRun
from jobs.models import Job
from jobs.settings import Settings

BERLIN = ZoneInfo("Europe/Berlin")
# Europe/Berlin in 2026: on 29 March 02:00 CET becomes 03:00 CEST (no 02:xx that night);
# on 25 October 03:00 CEST becomes 02:00 CET (02:xx twice).
FORWARD = datetime(2026, 3, 29, 1, 0, tzinfo=UTC)
BACK = datetime(2026, 10, 25, 1, 0, tzinfo=UTC)
TICK = timedelta(minutes=2)  # coarser than the 30 s of DNCQ_SCHEDULE_TICK_S: fewer ticks


def _schedule(settings: Settings, cron: str, zone: str = "Europe/Berlin") -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        schedules.upsert(session=session, data_dir=settings.data_dir,
                         schedule_in=schedules.ScheduleIn(name="s", cron=cron, timezone=zone))
        session.execute(update(Schedule).values(created_at=datetime(2026, 1, 1, tzinfo=UTC)))


def _night(settings: Any, add_machines: Any, cron: str, change: datetime) -> list[str]:
    """The backups the scheduler starts for fire times from 3 h before `change` to 3 h
    after, as the schedule's wall clock shows each; one job each."""
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    _schedule(settings, cron)
    now = change - timedelta(hours=3) + timedelta(seconds=30)
    schedules.tick(settings=settings, now=now)  # the last one before, owed since January
    started = []
    while now < change + timedelta(hours=3):
        now += TICK
        started += schedules.tick(settings=settings, now=now)
    with db.session_scope(settings.resolved_database_url) as session:
        fired = [(r.fire_at, r.job_id) for r in session.scalars(
            select(ScheduleRun).where(ScheduleRun.fire_at > change - timedelta(hours=3))
            .order_by(ScheduleRun.fire_at))]
        jobs = session.scalars(select(Job.id).where(Job.id.in_(started))).all()
    assert sorted(jobs) == sorted(started) == sorted(job for _, job in fired)
    return [f"{fire.astimezone(BERLIN):%d %H:%M%z}" for fire, _ in fired]


def test_a_nightly_backup_in_the_hour_the_clocks_skip_runs_once_as_they_change(
        settings, add_machines):
    assert _night(settings, add_machines, "30 2 * * *", FORWARD) == ["29 03:00+0200"]


def test_a_nightly_backup_in_the_hour_the_clocks_repeat_runs_once(settings, add_machines):
    assert _night(settings, add_machines, "30 2 * * *", BACK) == ["25 02:30+0200"]


def test_an_hourly_backup_runs_once_in_each_real_hour_when_the_clocks_go_forward(
        settings, add_machines):
    assert _night(settings, add_machines, "0 * * * *", FORWARD) == [
        "29 00:00+0100", "29 01:00+0100", "29 03:00+0200", "29 04:00+0200", "29 05:00+0200",
        "29 06:00+0200"]


def test_an_hourly_backup_runs_once_in_each_real_hour_when_the_clocks_go_back_the_repeated_too(
        settings, add_machines):
    assert _night(settings, add_machines, "0 * * * *", BACK) == [
        "25 01:00+0200", "25 02:00+0200", "25 02:00+0100", "25 03:00+0100", "25 04:00+0100",
        "25 05:00+0100"]


def _by_the_minute(cron: str, zone: ZoneInfo, start: datetime, end: datetime) -> list[datetime]:
    """The fire times in (start, end], found minute by minute on the zone's clock: each
    minute the cron names; a minute the clocks skipped, at the change, for a schedule
    limited to some hours; a repeated minute again only for one that runs every hour."""
    minutes, hours, *days = croniter(cron).expanded
    assert days == [["*"]] * 3  # the crons below name minutes and hours alone

    def named(wall: datetime) -> bool:
        return ((minutes == ["*"] or wall.minute in minutes)
                and (hours == ["*"] or wall.hour in hours))

    fixed = hours != ["*"]
    fires = []
    minute = start.replace(second=0, microsecond=0)
    before = minute.astimezone(zone).replace(tzinfo=None, fold=0)
    while (minute := minute + timedelta(minutes=1)) <= end:
        shown = minute.astimezone(zone)
        wall = shown.replace(tzinfo=None, fold=0)
        skipped = [before + timedelta(minutes=n)
                   for n in range(1, (wall - before) // timedelta(minutes=1))]
        if (named(wall) and not (fixed and shown.fold)) or (
                fixed and any(named(m) for m in skipped)):
            fires.append(minute)
        before = wall
    return fires


ZONES = ["Europe/Berlin", "America/New_York", "Australia/Lord_Howe", "America/Santiago"]
CRONS = ["30 2 * * *", "0 3 * * *", "0 1-3 * * *", "0 * * * *", "*/20 * * * *"]


def _changes(zone: ZoneInfo) -> list[datetime]:
    """The instants in 2026 at which the zone's offset changes, to the hour."""
    hours = [datetime(2026, 1, 1, tzinfo=UTC) + timedelta(hours=n) for n in range(365 * 24)]
    return [h for h, after in zip(hours, hours[1:], strict=False)
            if h.astimezone(zone).utcoffset() != after.astimezone(zone).utcoffset()]


@pytest.mark.parametrize("zone_name", ZONES)
def test_fire_times_next_and_last_are_the_wall_clocks_around_every_change(zone_name):
    # Lord Howe moves its clocks by 30 minutes, Santiago's change at midnight: the rules
    # are the same, reckoned from the zone's offsets, not from croniter's own handling of a
    # zone (before 6.2, which pyproject allows, hourly schedules lost the repeated hour).
    zone = ZoneInfo(zone_name)
    for change in _changes(zone):
        start, end = change - timedelta(hours=4), change + timedelta(hours=4)
        for cron in CRONS:
            expected = _by_the_minute(cron, zone, start - timedelta(days=1),
                                      end + timedelta(days=1))
            walked = []
            for fire in fire_times.fires_after(cron, zone, start):
                if fire > end:
                    break
                walked.append(fire)
            assert walked == [f for f in expected if start < f <= end], (zone_name, cron)
            now = start
            while now < end:
                assert fire_times.last_fire(cron, zone, now) == max(
                    f for f in expected if f <= now), (zone_name, cron, now)
                assert fire_times.next_fire(cron, zone, now) == min(
                    f for f in expected if f > now), (zone_name, cron, now)
                now += timedelta(minutes=17, seconds=11)
